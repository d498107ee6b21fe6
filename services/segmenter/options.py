"""CLIPSeg options that configs and the CLI name without importing torch.

`clipseg.py` (which loads torch) and `core.py` (which must not, so the onboard image and
`--help` stay light) both read them from here.
"""

DEFAULT_MODEL = "CIDAS/clipseg-rd64-refined"  # Hub id of the reference's weights
DTYPES = ("float32", "bfloat16")  # inference dtypes the fast path supports
# CLIPSeg variants (see backends.py): `auto` times the ones this host can run and keeps the fastest
# that passes the decision gate; a name pins one.
CLIPSEG_VARIANTS = ("auto", "fp32", "bf16", "onnx-int8", "cuda-fp16")
