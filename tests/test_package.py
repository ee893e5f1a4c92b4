"""Tests of the package as distributed: the wheel's contents and the
registration of ``EBSD.refine_geometry_dic``.

The wheel is built from a copy of the source tree (so that the build
leaves nothing in the working tree) with ``pip wheel``, which fetches the
build backend from PyPI or pip's cache.
"""

from __future__ import annotations

import email
import inspect
import shutil
import subprocess
import sys
import types
import warnings
import zipfile
from pathlib import Path

import pytest
from kikuchipy.signals import EBSD, LazyEBSD

import kikuchipy_geomdic
from kikuchipy_geomdic.calibration.refinement import refine_geometry_dic

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kikuchipy_geomdic"


# --------------------------------------------------------------------- #
# Wheel
# --------------------------------------------------------------------- #


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> zipfile.ZipFile:
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(
        ROOT,
        src,
        ignore=shutil.ignore_patterns(
            ".git",
            "build",
            "dist",
            "*.egg-info",
            "__pycache__",
            ".pytest_cache",
            ".ruff_cache",
            "_build",
            "geomdic-demo",
            ".venv",
            ".ipynb_checkpoints",
        ),
    )
    res = subprocess.run(
        [sys.executable, "-m", "pip", "wheel", ".", "--no-deps", "-w", str(tmp / "dist")],
        cwd=src,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stdout + res.stderr
    (path,) = (tmp / "dist").glob("kikuchipy_geomdic-*.whl")
    with zipfile.ZipFile(path) as z:
        yield z


def test_wheel_holds_the_package_data(wheel):
    names = set(wheel.namelist())
    data = [
        "kikuchipy_geomdic/data/Si_dynamical.npz",
        "kikuchipy_geomdic/data/BaTiO3_dynamical.npz",
        "kikuchipy_geomdic/data/Si.cif",
        "kikuchipy_geomdic/data/BaTiO3.cif",
    ]
    missing = [n for n in data if n not in names]
    assert not missing, missing
    # Every data file of the source tree, and every module
    for path in [*(PACKAGE / "data").rglob("*"), *PACKAGE.rglob("*.py")]:
        if path.is_file() and "__pycache__" not in path.parts:
            name = path.relative_to(ROOT).as_posix()
            assert name in names, name
    # The data files are the same bytes
    for name in data:
        assert wheel.read(name) == (ROOT / name).read_bytes(), name
    assert not any(n.startswith(("tests/", "tutorials/", "docs/")) for n in names)


def test_wheel_ships_no_third_party_patterns(wheel):
    """kikuchipy's real silicon patterns (CC BY 4.0) are read through
    ``kikuchipy.data``; neither they nor any other pattern file is shipped."""
    names = wheel.namelist()
    assert not [n for n in names if "silicon_moving_screen" in n], names
    assert not [n for n in names if n.endswith((".h5", ".hdf5", ".h5ebsd"))], names
    assert not (PACKAGE / "data" / "silicon_moving_screen").exists()


def test_wheel_metadata(wheel):
    (meta_name,) = [n for n in wheel.namelist() if n.endswith(".dist-info/METADATA")]
    meta = email.message_from_bytes(wheel.read(meta_name))
    requires = meta.get_all("Requires-Dist")
    default = [r for r in requires if "extra ==" not in r]
    assert any(r.startswith("opencv-python-headless") for r in default), default
    assert any(r.startswith("scikit-image") for r in default), default
    assert meta["Requires-Python"] == ">=3.10"
    (ep_name,) = [n for n in wheel.namelist() if n.endswith(".dist-info/entry_points.txt")]
    assert "kikuchipy-geomdic = kikuchipy_geomdic.cli:main" in wheel.read(ep_name).decode()


# --------------------------------------------------------------------- #
# EBSD.refine_geometry_dic
# --------------------------------------------------------------------- #


def test_method_is_the_function_with_its_signature():
    assert EBSD.refine_geometry_dic is refine_geometry_dic
    assert LazyEBSD.refine_geometry_dic is refine_geometry_dic
    params = inspect.signature(EBSD.refine_geometry_dic).parameters
    assert list(params)[:5] == ["signal", "xmap", "detector", "master_pattern", "energy"]
    assert "parameters" in params and "points" in params and "max_iterations" in params
    assert not any(p.kind is p.VAR_KEYWORD for p in params.values())
    # Bound to a signal, the signal is self
    s = EBSD.__new__(EBSD)
    bound = inspect.signature(s.refine_geometry_dic).parameters
    assert list(bound)[0] == "xmap" and "points" in bound
    assert EBSD.refine_geometry_dic.__doc__ == refine_geometry_dic.__doc__


def test_registering_again_changes_nothing():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kikuchipy_geomdic._register()
    assert EBSD.refine_geometry_dic is refine_geometry_dic


def test_registration_replaces_an_earlier_import_of_ours(monkeypatch):
    """After a module reload (importlib.reload, IPython autoreload)."""
    f = refine_geometry_dic
    old = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
    old.__qualname__, old.__module__ = f.__qualname__, f.__module__
    monkeypatch.setattr(EBSD, "refine_geometry_dic", old)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        kikuchipy_geomdic._register()
    assert EBSD.refine_geometry_dic is refine_geometry_dic


def test_registration_leaves_a_foreign_method_alone(monkeypatch):
    def refine_geometry_dic(self, *args, **kwargs):  # e.g. a future kikuchipy's
        return "kikuchipy's"

    monkeypatch.setattr(EBSD, "refine_geometry_dic", refine_geometry_dic)
    with pytest.warns(UserWarning, match="already has a refine_geometry_dic"):
        kikuchipy_geomdic._register()
    assert EBSD.refine_geometry_dic is refine_geometry_dic


def test_reindex_is_a_method_too():
    from kikuchipy_geomdic.indexing.reindex import reindex

    assert EBSD.reindex is reindex
    assert LazyEBSD.reindex is reindex
    assert "signal" in inspect.signature(reindex).parameters


# --------------------------------------------------------------------- #
# Layers
# --------------------------------------------------------------------- #

#: The package's layers, bottom first (the package docstring says what each
#: holds). A module may import from its own layer and those below.
LAYERS = (
    "_version",
    "geometry",
    "io",
    "patterns",
    "indexing",
    "plotting",
    "calibration",
    "validation",
    "cli",
)


def _layer(module: str) -> int:
    """Layer of a dotted module name inside the package; the package's own
    ``__init__`` and ``__main__`` sit above every layer."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] in ("__init__", "__main__"):
        return len(LAYERS)
    return LAYERS.index(parts[1])


def _imports(path: Path) -> list[tuple[int, str]]:
    """Every import of the package in *path*, also those inside functions."""
    import ast

    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.level:
                raise AssertionError(f"{path}: relative import at line {node.lineno}")
            if node.module == "kikuchipy_geomdic":
                found += [(node.lineno, f"kikuchipy_geomdic.{a.name}") for a in node.names]
            elif node.module.startswith("kikuchipy_geomdic."):
                found.append((node.lineno, node.module))
        elif isinstance(node, ast.Import):
            found += [
                (node.lineno, a.name) for a in node.names if a.name.startswith("kikuchipy_geomdic")
            ]
    return found


def test_no_module_imports_a_layer_above_its_own():
    modules = sorted(PACKAGE.rglob("*.py"))
    assert len(modules) > 20
    wrong = []
    for path in modules:
        name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        own = _layer(name)
        for line, imported in _imports(path):
            if _layer(imported) > own:
                wrong.append(f"{name}:{line} imports {imported}")
    assert not wrong, "\n".join(wrong)


def test_every_layer_is_a_known_subpackage():
    found = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").is_file()}
    found |= {p.stem for p in PACKAGE.glob("_*.py") if p.stem not in ("__init__", "__main__")}
    assert found == set(LAYERS)


# --------------------------------------------------------------------- #
# Sizes: small modules, thin public functions
# --------------------------------------------------------------------- #

#: Longest module (lines) and public function (lines of code: docstring,
#: blank and comment lines aside) the package keeps to.
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _code_lines(node, source: list[str]) -> int:
    import ast

    body = node.body
    first = body[0]
    if isinstance(first, ast.Expr) and isinstance(getattr(first, "value", None), ast.Constant):
        body = body[1:]
    lines = set()
    for statement in body:
        for number in range(statement.lineno, statement.end_lineno + 1):
            text = source[number - 1].strip()
            if text and not text.startswith("#"):
                lines.add(number)
    return len(lines)


def test_modules_are_small():
    long = {
        p.relative_to(ROOT).as_posix(): n
        for p in PACKAGE.rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert not long, long


def test_public_functions_are_thin():
    import ast

    long = {}
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        source = text.splitlines()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef) and not node.name.startswith("_"):
                if (n := _code_lines(node, source)) > MAX_FUNCTION_LINES:
                    long[f"{path.relative_to(ROOT).as_posix()}:{node.name}"] = n
    assert not long, long
