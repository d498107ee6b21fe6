"""The policy registry: one entry per policy, built by name, and no import cycle to dodge."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from dovesei.controller.policies.config_file import policy_values, preset_config
from dovesei.controller.policies.registry import POLICIES, entry, make_policy, policy_names

POLICIES_DIR = Path(__file__).resolve().parents[2] / "services" / "controller" / "policies"


def _module_of(path: Path) -> str:
    parts = path.relative_to(POLICIES_DIR).with_suffix("").parts
    parts = parts[:-1] if parts[-1] == "__init__" else parts
    return ".".join(("dovesei.controller.policies", *parts))


MODULES = sorted(_module_of(p) for p in POLICIES_DIR.rglob("*.py"))


@pytest.mark.parametrize("name", policy_names())
def test_every_entry_builds_its_policy_with_its_own_config_type(name: str) -> None:
    found = entry(name)
    assert found.name == name
    for timing in ("real", "reference"):
        config = found.preset(timing)
        assert isinstance(config, found.config_type)
        policy = make_policy(name, config)
        assert policy.name == name and isinstance(policy.config, found.config_type)
    # config_file reads the same entry: its preset and its settable values come from the registry.
    assert type(preset_config(name, "real")) is found.config_type and policy_values(name, found.preset("real"))


def test_an_unknown_name_is_one_error_listing_the_known_ones() -> None:
    with pytest.raises(ValueError, match="unknown policy 'nope'; known: clearance, dovesei, dovesei-nofocus"):
        make_policy("nope")
    assert sorted(POLICIES) == policy_names()


def test_the_contract_imports_no_policy_and_no_policy_module_imports_inside_a_function() -> None:
    base = ast.parse((POLICIES_DIR / "base.py").read_text(encoding="utf-8"))
    imported = {n.module for n in ast.walk(base) if isinstance(n, ast.ImportFrom) and n.module}
    assert not {m for m in imported if m.startswith("dovesei.controller")}, imported
    hidden = []
    for path in POLICIES_DIR.rglob("*.py"):
        for fn in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                hidden += [f"{path.name}:{n.lineno}" for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert not hidden, f"imports inside functions (a dodged cycle?): {hidden}"


def test_each_policy_module_imports_first_in_a_fresh_interpreter() -> None:
    # A cycle shows only for the module imported first: try each one first, in its own process.
    code = ("import importlib, subprocess, sys\n"
            "bad = []\n"
            "for m in sys.argv[1:]:\n"
            "    r = subprocess.run([sys.executable, '-c', f'import {m}'], capture_output=True, text=True)\n"
            "    if r.returncode: bad.append(m + ': ' + r.stderr.strip().splitlines()[-1])\n"
            "print('\\n'.join(bad))\n")
    assert len(MODULES) >= 12 and "dovesei.controller.policies.registry" in MODULES
    res = subprocess.run([sys.executable, "-c", code, *MODULES], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0 and res.stdout.strip() == "", res.stdout + res.stderr
