"""House rules that keep the repository standing alone (issue 9), checked on the source itself.

- Each service stands alone: product code (`services/**`, `shared/**`) imports only
  `dovesei.shared` and its own package, never another service and never the CLI layer
  (`dovesei.cli`, `dovesei.up`, `dovesei.testing`, `dovesei.benchmarks`, `dovesei.pictures`, ...).
  `dovesei.shared` imports no service at all.
- Imports of project modules sit at module top; one inside a function needs a reason on its line
  or just above it (``# lazy: <why>``), or an `except ImportError` around it (an optional
  dependency, named by the handler). Third-party imports inside functions (torch, transformers,
  cv2, pymavlink when a mode needs them) are the usual optional-dependency pattern, not counted.
- Nothing tracked refers to the team's machines: no `../shared`, no `/work/`, no home folders.
- Packaging matches the tree: every declared package exists, every package folder is declared,
  every package-data pattern matches a file.
"""

from __future__ import annotations

import ast
import io
import re
import subprocess
import tokenize
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
PACKAGE_DIRS: dict[str, str] = PYPROJECT["tool"]["setuptools"]["package-dir"]


def _package_of(path: Path) -> str:
    """The dotted package a product file belongs to (dovesei.shared, dovesei.sim, ...)."""
    rel = path.relative_to(ROOT).as_posix()
    best = max((d for d in PACKAGE_DIRS.values() if rel.startswith(d + "/")), key=len)
    pkg = next(name for name, d in PACKAGE_DIRS.items() if d == best)
    sub = Path(rel[len(best) + 1:]).parent.parts
    return ".".join((pkg, *sub))


def _product_files() -> list[Path]:
    files = sorted((ROOT / "shared").rglob("*.py")) + sorted((ROOT / "services").rglob("*.py"))
    return [f for f in files if "__pycache__" not in f.parts]


PRODUCT = _product_files()


def _imports(tree: ast.AST, package: str):
    """(node, absolute module name, inside a function?) for every import in `tree`."""
    def walk(node: ast.AST, in_function: bool):
        for child in ast.iter_child_nodes(node):
            nested = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for alias in child.names:
                    yield child, alias.name, in_function
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = package.split(".")
                    base = base[: len(base) - (child.level - 1)]
                    module = ".".join(base + ([child.module] if child.module else []))
                else:
                    module = child.module or ""
                yield child, module, in_function
            yield from walk(child, nested)
    yield from walk(tree, False)


def _own_root(package: str) -> str:
    """dovesei.controller.policies -> dovesei.controller: a service may import all of itself."""
    return ".".join(package.split(".")[:2])


def _allowed(module: str, package: str) -> bool:
    if module != "dovesei" and not module.startswith("dovesei."):
        return True  # third party or stdlib
    own = _own_root(package)
    if own == "dovesei.shared":
        return module == own or module.startswith(own + ".")
    return any(module == p or module.startswith(p + ".") for p in ("dovesei.shared", own))


def test_the_product_files_are_found() -> None:
    packages = {_own_root(_package_of(f)) for f in PRODUCT}
    assert {"dovesei.shared", "dovesei.sim", "dovesei.segmenter", "dovesei.controller"} <= packages


@pytest.mark.parametrize("path", PRODUCT, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_a_service_imports_only_shared_and_itself(path: Path) -> None:
    package = _package_of(path)
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    bad = [f"line {node.lineno}: {module}" for node, module, _ in _imports(tree, package)
           if not _allowed(module, package)]
    assert not bad, f"{path.relative_to(ROOT)} ({package}) imports outside dovesei.shared and itself: {bad}"


def _guarded_imports(tree: ast.AST) -> set[int]:
    """ids of imports in the body of a `try` that catches ImportError: an optional dependency,
    whose handler says what is missing, which is reason enough to import late."""
    names = {"ImportError", "ModuleNotFoundError"}
    guarded: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try) and any(
                isinstance(h.type, ast.Name) and h.type.id in names
                or isinstance(h.type, ast.Tuple) and any(isinstance(e, ast.Name) and e.id in names for e in h.type.elts)
                for h in node.handlers):
            guarded |= {id(n) for stmt in node.body for n in ast.walk(stmt) if isinstance(n, (ast.Import, ast.ImportFrom))}
    return guarded


def _has_lazy_reason(lines: list[str], node: ast.stmt) -> bool:
    """A '# lazy:' comment on the import's own lines, or in the comment just above it (which may
    head a group of imports: the lines between are comments or imports)."""
    if any("# lazy:" in line for line in lines[node.lineno - 1: (node.end_lineno or node.lineno)]):
        return True
    i = node.lineno - 2
    while i >= 0:
        text = lines[i].strip()
        if "# lazy:" in text:
            return True
        if not (text.startswith(("#", "from ", "import ")) or text.startswith(")")):
            return False
        i -= 1
    return False


@pytest.mark.parametrize("path", PRODUCT, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_project_imports_inside_functions_state_a_reason(path: Path) -> None:
    package = _package_of(path)
    lines = path.read_text(encoding="utf-8").splitlines()
    tree = ast.parse("\n".join(lines), filename=str(path))
    hidden = []
    guarded = _guarded_imports(tree)
    for node, module, in_function in _imports(tree, package):
        if not in_function or not (module == "dovesei" or module.startswith("dovesei.")) or id(node) in guarded:
            continue
        if not _has_lazy_reason(lines, node):
            hidden.append(f"line {node.lineno}: {module}")
    assert not hidden, (f"{path.relative_to(ROOT)}: project imports inside functions without a "
                        f"'# lazy: <reason>' comment (move them to the top): {hidden}")


def test_the_checker_sees_what_it_should() -> None:
    # The walk itself: relative imports resolve, function-level imports are told apart.
    src = ("from . import core\nfrom ..shared import keys\nimport dovesei.controller.mavlink\n"
           "def f():\n    from dovesei.sim.world import load_world  # lazy: test\n")
    found = [(m, inside) for _, m, inside in _imports(ast.parse(src), "dovesei.segmenter")]
    assert found == [("dovesei.segmenter", False), ("dovesei.shared", False), ("dovesei.controller.mavlink", False),
                     ("dovesei.sim.world", True)]
    assert _allowed("dovesei.shared.keys", "dovesei.sim") and _allowed("dovesei.sim.core", "dovesei.sim")
    assert not _allowed("dovesei.controller.mavlink", "dovesei.sim")
    assert not _allowed("dovesei.testing.fake_autopilot", "dovesei.controller")
    assert not _allowed("dovesei.sim.world", "dovesei.shared")
    assert not _allowed("dovesei", "dovesei.sim")
    assert _package_of(ROOT / "services/controller/policies/base.py") == "dovesei.controller.policies"
    lines = ["def f():", "    # lazy: torch only here", "    from . import a", "    from . import b",
             "    x = 1", "    from . import c"]
    tree = ast.parse("\n".join(lines))
    reasons = [_has_lazy_reason(lines, node) for node, _, _ in _imports(tree, "dovesei.segmenter")]
    assert reasons == [True, True, False]
    optional = ast.parse("def f():\n    try:\n        from . import onnx\n    except ImportError:\n        pass\n"
                         "    from . import other\n")
    assert [id(n) in _guarded_imports(optional) for n, _, _ in _imports(optional, "dovesei.segmenter")] == [True, False]


# ---------------------------------------------------------------------------------- paths

# Paths of the team's machines (and folders beside the repository) that a clean clone lacks.
# /home/nobody is the home of the container's user (deploy/Dockerfile: USER nobody), inside the image.
FORBIDDEN = [r"\.\./shared\b", r"(?<![\w.])/work/", r"(?<![\w.])/home/(?!nobody/)\w", r"(?<![\w.])/Users/\w",
             r"(?<![\w.])/root/", r"\b[A-Z]:\\\\Users"]


# Not part of a checkout: what a source tree outside git (an sdist, a copied folder) may carry.
_UNTRACKED = {".git", ".venv", "__pycache__", ".pytest_cache", ".hypothesis", "build", "runs", "out", "models"}


def _tracked() -> list[str]:
    """The repository's files: git's list in a checkout, else the tree less the usual build output."""
    if (ROOT / ".git").exists():
        res = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, timeout=60)
        if res.returncode != 0:
            pytest.fail(f"git ls-files failed: {res.stderr.decode(errors='replace')}")
        return [p for p in res.stdout.decode().split("\0") if p]
    return sorted(p.relative_to(ROOT).as_posix() for p in ROOT.rglob("*")
                  if p.is_file() and not (_UNTRACKED & set(p.relative_to(ROOT).parts))
                  and not any(part.endswith(".egg-info") for part in p.parts))


def test_nothing_tracked_refers_to_the_teams_machines() -> None:
    pattern = re.compile("|".join(FORBIDDEN))
    me = Path(__file__).resolve().relative_to(ROOT).as_posix()
    offenders = []
    for rel in _tracked():
        path = ROOT / rel
        if rel == me or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:
            continue  # binary (images, label maps)
        for n, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            if pattern.search(line):
                offenders.append(f"{rel}:{n}: {line.strip()[:120]}")
    assert not offenders, "paths outside the repository:\n" + "\n".join(offenders)


def test_the_path_patterns_catch_what_they_should() -> None:
    pattern = re.compile("|".join(FORBIDDEN))
    for bad in ("see ../shared/REFERENCE.md", 'Path("/work/shared/worlds")', "/home/alice/x", "cd /root/x"):
        assert pattern.search(bad), bad
    for fine in ("deploy/zenoh/router.json5", "/etc/zenoh/router.json5", "/dev/video0", "a/work/b",
                 "worlds:/home/nobody/.cache/dovesei",
                 "https://example.org/work/x"):
        assert not pattern.search(fine), fine


# ---------------------------------------------------------------------------------- packaging


def test_every_declared_package_exists_and_every_package_is_declared() -> None:
    declared = set(PYPROJECT["tool"]["setuptools"]["packages"])

    def folder(pkg: str) -> Path:
        parts = pkg.split(".")
        for i in range(len(parts), 0, -1):
            head = ".".join(parts[:i])
            if head in PACKAGE_DIRS:
                return ROOT / PACKAGE_DIRS[head] / Path(*parts[i:])
        return ROOT / Path(*parts)

    missing = [p for p in sorted(declared) if not (folder(p) / "__init__.py").is_file()]
    assert not missing, f"declared in pyproject.toml but no package folder: {missing}"
    on_disk = set()
    for pkg, d in PACKAGE_DIRS.items():
        for init in (ROOT / d).rglob("__init__.py"):
            if "__pycache__" in init.parts:
                continue
            sub = init.parent.relative_to(ROOT / d).parts
            name = ".".join((pkg, *sub))
            # A folder mapped to its own package-dir entry is that package, not a subpackage here.
            if not any(name != p and (ROOT / PACKAGE_DIRS[p]) == init.parent for p in PACKAGE_DIRS):
                on_disk.add(name)
    undeclared = sorted(on_disk - declared)
    assert not undeclared, f"package folders missing from pyproject.toml packages (a wheel would lack them): {undeclared}"


def test_every_package_data_pattern_matches_files() -> None:
    data: dict[str, list[str]] = PYPROJECT["tool"]["setuptools"].get("package-data", {})
    assert data, "the Dubai world is package data of dovesei.sim"
    for pkg, patterns in data.items():
        base = ROOT / PACKAGE_DIRS.get(pkg, pkg.replace(".", "/"))
        assert base.is_dir(), f"package-data for {pkg}: no folder {base.relative_to(ROOT)}"
        for pattern in patterns:
            matches = [p for p in base.glob(pattern) if p.is_file()]
            assert matches, f"package-data {pkg}: {pattern!r} matches no file under {base.relative_to(ROOT)}"


# ------------------------------------------------------------------ one owner per mission constant
#
# The hand-over altitude, the safety radius and the separations have their one default in shared/mission.py, the
# camera footprint its one formula in shared/footprint.py (issue 27: the hand-over was declared
# four times and `--handover-alt-m` never reached `clearance`; the footprint was written in eight
# places). Everything else receives the value from its parent object or calls the helper.

MISSION_MODULE = "shared/mission.py"
FOOTPRINT_MODULE = "shared/footprint.py"
_MISSION_NAME = re.compile(r"hand_?over_alt|safety_radius|separation_m", re.IGNORECASE)
_HANDOVER_WORD = re.compile(r"hand-?_?over", re.IGNORECASE)
_TWENTY_M_TEXT = re.compile(r"\b20(\.0)?\s*m\b")


def _code_files() -> list[Path]:
    files = [f for top in ("shared", "services", "dovesei") for f in sorted((ROOT / top).rglob("*.py"))]
    return [f for f in files if "__pycache__" not in f.parts]


def _is_number(node: ast.AST | None) -> bool:
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        node = node.operand
    return isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool)


def _target_names(node: ast.AST) -> list[str]:
    if isinstance(node, ast.Name):
        return [node.id]
    if isinstance(node, ast.Attribute):
        return [node.attr]
    if isinstance(node, (ast.Tuple, ast.List)):
        return [n for elt in node.elts for n in _target_names(elt)]
    return []


def mission_literals(source: str) -> list[str]:
    """'line: name' for every numeric default of a mission constant declared in `source`: an
    assignment, a parameter default, or a `.get(name, number)` / `getattr(x, name, number)` fallback."""
    found = []
    for node in ast.walk(ast.parse(source)):
        pairs: list[tuple[str, ast.AST | None]] = []
        if isinstance(node, ast.AnnAssign):
            pairs = [(n, node.value) for n in _target_names(node.target)]
        elif isinstance(node, ast.Assign):
            pairs = [(n, node.value) for t in node.targets for n in _target_names(t)]
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            a = node.args
            positional = a.posonlyargs + a.args
            pairs = [(arg.arg, d) for arg, d in zip(positional[len(positional) - len(a.defaults):], a.defaults)]
            pairs += [(arg.arg, d) for arg, d in zip(a.kwonlyargs, a.kw_defaults)]
        elif isinstance(node, ast.Call):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name in ("get", "getattr", "pop", "setdefault"):
                keys_ = [a.value for a in node.args if isinstance(a, ast.Constant) and isinstance(a.value, str)]
                pairs = [(k, a) for k in keys_ for a in node.args if _is_number(a)]
        found += [f"{node.lineno}: {n}" for n, value in pairs if _MISSION_NAME.search(n) and _is_number(value)]
    return found


def handover_twenties(source: str) -> list[str]:
    """'line: text' for every code line (comments aside) that speaks of the hand-over with a 20 in it."""
    lines: dict[int, list[tokenize.TokenInfo]] = {}
    for tok in tokenize.generate_tokens(io.StringIO(source).readline):
        if tok.type != tokenize.COMMENT:
            lines.setdefault(tok.start[0], []).append(tok)
    found = []
    for n, toks in lines.items():
        if not any(_HANDOVER_WORD.search(t.string) for t in toks):
            continue
        if any(t.type == tokenize.NUMBER and float(t.string) == 20.0 for t in toks) or \
                any(t.type == tokenize.STRING and _TWENTY_M_TEXT.search(t.string) for t in toks):
            found.append(f"{n}: {''.join(t.string for t in toks).strip()[:100]}")
    return found


def footprint_formulas(source: str) -> list[str]:
    """'line: call' for every tan(...) of a field of view: the footprint formula written again."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Call) and node.args:
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name == "tan" and "fov" in ast.unparse(node.args[0]).lower():
                found.append(f"{node.lineno}: {ast.unparse(node)}")
    return found


def test_mission_constants_have_one_literal_default() -> None:
    offenders = []
    for path in _code_files():
        rel = path.relative_to(ROOT).as_posix()
        source = path.read_text(encoding="utf-8")
        if rel != MISSION_MODULE:
            offenders += [f"{rel}:{hit}" for hit in mission_literals(source) + handover_twenties(source)]
        if rel != FOOTPRINT_MODULE:
            offenders += [f"{rel}:{hit} (use dovesei.shared.footprint)" for hit in footprint_formulas(source)]
    assert not offenders, ("a mission constant or the footprint formula written outside shared/mission.py and "
                           "shared/footprint.py:\n" + "\n".join(offenders))


def test_the_mission_checkers_see_what_they_should() -> None:
    bad = '''
from dataclasses import dataclass
HANDOVER_ALT_M = 20.0
@dataclass
class C:
    handover_alt_m: float = 20.0
    safety_radius_m: float = -2.0
def f(x, safety_radius_m=2.0, *, handover_alt_m: float = 20): ...
r = report.get("handover_alt_m", 20.0)
s = getattr(cfg, "safety_radius_m", 2)
'''
    assert sorted(h.split(": ")[1] for h in mission_literals(bad)) == sorted([
        "HANDOVER_ALT_M", "handover_alt_m", "safety_radius_m", "safety_radius_m", "handover_alt_m",
        "handover_alt_m", "safety_radius_m"]), mission_literals(bad)
    fine = '''
from dovesei.shared.mission import HANDOVER_ALT_M
handover_alt_m: float = HANDOVER_ALT_M
core = SimConfig(handover_alt_m=5.0)  # a caller's choice, not a default
r = report.get("handover_alt_m", HANDOVER_ALT_M)
'''
    assert mission_literals(fine) == []
    assert len(handover_twenties('x = alt if ok else 20.0  # the hand-over\nmsg = "the hand-over is at 20 m"\n'
                                 'y = handover_m + 20\n')) == 2
    assert handover_twenties("# the hand-over is at 20 m\nz = 20.0\n") == []
    assert len(footprint_formulas("import math\na = math.tan(hfov_rad / 2.0) * alt\n"
                                  "b = tan(cam.hfov_rad / 2)\nc = math.tan(pitch_rad)\n")) == 2
