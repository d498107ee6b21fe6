"""What the CPU can do fast, read from the CPU itself (never assumed from a model name).

bfloat16 is only worth timing where the CPU has native BF16 arithmetic (AVX-512 BF16 or AMX
BF16): elsewhere torch emulates it and it ran 3-10x slower than float32 on the team's Xeon.
int8 is fast with VNNI (AVX-512 VNNI or AVX-VNNI) and still usable with plain AVX2. The flags
come from /proc/cpuinfo (Linux); `native_bf16` also asks oneDNN through torch when the caller
passes its answer, and both must agree, so neither a kernel that hides flags nor a torch build
without BF16 kernels makes bf16 look native. No torch import here: the onboard install has none.
"""

from __future__ import annotations

from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")
BF16_FLAGS = ("avx512_bf16", "amx_bf16")
VNNI_FLAGS = ("avx512_vnni", "avx_vnni")
REPORTED_FLAGS = ("avx2", "fma", "f16c", "avx512f", *VNNI_FLAGS, *BF16_FLAGS, "amx_tile", "amx_int8")


def cpu_flags(cpuinfo: Path = CPUINFO) -> frozenset[str]:
    """The flags of the first CPU in /proc/cpuinfo; empty when the file is missing (not Linux)."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return frozenset()
    for line in text.splitlines():
        name, _, value = line.partition(":")
        if name.strip() in ("flags", "Features"):  # x86 / ARM spelling
            return frozenset(value.split())
    return frozenset()


def cpu_model(cpuinfo: Path = CPUINFO) -> str:
    try:
        for line in cpuinfo.read_text().splitlines():
            name, _, value = line.partition(":")
            if name.strip() == "model name":
                return value.strip()
    except OSError:
        pass
    return "unknown"


def native_bf16(flags: frozenset[str], onednn_bf16: bool | None = None) -> tuple[bool, str]:
    """(True, why) when bf16 arithmetic is native here; `onednn_bf16` is torch's own answer."""
    have = [f for f in BF16_FLAGS if f in flags]
    if not have:
        return False, f"CPU flags have none of {', '.join(BF16_FLAGS)}"
    if onednn_bf16 is False:
        return False, f"CPU flags {', '.join(have)} but torch's oneDNN reports no bf16 support"
    return True, f"CPU flags {', '.join(have)}" + ("" if onednn_bf16 is None else ", oneDNN bf16 supported")


def summary(flags: frozenset[str]) -> dict[str, object]:
    """The flags that decide the candidates, for logs and the benchmark's JSON."""
    return {"model": cpu_model(), "flags": sorted(f for f in REPORTED_FLAGS if f in flags),
            "native_bf16": native_bf16(flags)[0], "vnni": any(f in flags for f in VNNI_FLAGS)}
