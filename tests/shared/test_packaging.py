"""The onboard install has no torch: controller, sim and the CLI's light commands import without it."""

from __future__ import annotations

import subprocess
import sys

# `sys.modules[name] = None` makes `import name` fail exactly as on a machine without the package.
NO_TORCH = "import sys; sys.modules['torch'] = None; sys.modules['transformers'] = None; "


def _python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", NO_TORCH + code], capture_output=True, text=True, timeout=120)


def test_controller_and_sim_import_without_torch() -> None:
    res = _python("import dovesei.controller, dovesei.sim, dovesei.controller.service, dovesei.sim.service, "
                  "dovesei.camera.service, dovesei.controller.mavlink.vehicle, dovesei.shared.codec; print('ok')")
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stderr


def test_simulated_segmenter_runs_without_torch() -> None:
    # The sim backend is what `dovesei up` falls back to; it must not need torch either.
    res = _python("from dovesei.segmenter.core import SegmenterConfig, make_backend; "
                  "b = make_backend(SegmenterConfig(backend='auto', model='/nonexistent')); print(b.name)")
    assert res.returncode == 0 and res.stdout.strip().endswith("simulated"), res.stderr


def test_torch_is_really_blocked_in_these_checks() -> None:
    res = _python("import torch")
    assert res.returncode != 0 and ("ModuleNotFoundError" in res.stderr or "ImportError" in res.stderr)
