"""CLIPSeg options that configs and the CLI name without importing torch.

`clipseg.py` (which loads torch) and `core.py` (which must not, so the onboard image and
`--help` stay light) both read them from here.
"""

DEFAULT_MODEL = "CIDAS/clipseg-rd64-refined"  # Hub id of the reference's weights
DTYPES = ("float32", "bfloat16")  # inference dtypes the fast path supports
