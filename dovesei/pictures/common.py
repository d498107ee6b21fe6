"""What every picture shares: the error type and how a perception backend is named on screen."""

from __future__ import annotations


class ReportError(ValueError):
    """The data handed to a picture function is unusable (empty path, wrong shape); says what."""


def backend_label(backend: str, simulated: bool, noise: float | None = None, profile: str | None = None) -> str:
    """How titles and logs name the perception: a simulated run must never pass for CLIPSeg."""
    if simulated:
        return ("simulated perception" + (f" {profile}" if profile else "")
                + (f" (noise {noise:g})" if noise is not None else ""))
    return backend or "unknown backend"
