"""`--backend auto` without CLIPSeg weights on disk falls back to the simulated perception without
importing torch: trying the load first cost 10-25 s of every `dovesei up` on a loaded 2-core host
(the segmenter's token came 27 s after its start) and a slow interpreter teardown after."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from dovesei.segmenter.core import weights_missing

REPO = Path(__file__).resolve().parents[2]
NOT_CACHED = "dovesei-tests/no-such-clipseg"  # a Hub id no cache holds


def test_weights_missing_reads_the_folder_or_the_offline_cache(tmp_path: Path) -> None:
    assert "no such local directory" in weights_missing(str(tmp_path / "absent"))
    (tmp_path / "m").mkdir()
    assert "no config.json" in weights_missing(str(tmp_path / "m"))
    (tmp_path / "m" / "config.json").write_text("{}")
    assert weights_missing(str(tmp_path / "m")) is None  # there: the real load decides
    assert "HF_HUB_OFFLINE" in weights_missing(NOT_CACHED, env={"HF_HUB_OFFLINE": "1"})
    assert weights_missing(NOT_CACHED, env={}) is None  # online the Hub may have it
    assert weights_missing(NOT_CACHED, env={"HF_HUB_OFFLINE": "0"}) is None


def test_auto_without_weights_never_imports_torch() -> None:
    code = ("import json, sys\n"
            "from dovesei.segmenter.core import SegmenterConfig, make_backend\n"
            f"backend = make_backend(SegmenterConfig(backend='auto', model={NOT_CACHED!r}))\n"
            "print(json.dumps({'simulated': backend.simulated, 'reason': backend.reason,\n"
            "                  'torch': 'torch' in sys.modules, 'transformers': 'transformers' in sys.modules}))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300,
                          env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got["simulated"] and "fell back to simulated" in got["reason"] and NOT_CACHED in got["reason"]
    assert not got["torch"] and not got["transformers"], got
