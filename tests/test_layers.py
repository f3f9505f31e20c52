"""The layers of mavvo: every import points down, and each outside library has one importer.

Layers, lowest first (``docs/design.md``): the shared vocabulary (``mavvo.errors``, ``mavvo.options``,
``mavvo.types``, ``mavvo.jit``), ``mavvo.geometry``, ``mavvo.estimation``, ``mavvo.odometry``,
``mavvo.service``, ``mavvo.calibration``, ``mavvo.evaluation``, the simulator's ``mavvo.sim.world``,
``mavvo.sim.flight_controller`` and ``mavvo.sim.scenarios``, ``mavvo.offline``, the command line
(``mavvo.cli``, ``mavvo.commands``), and outside the package, at the top, the developer tooling under
``tools/`` (the fault suite drives the command line as an operator would). The commands import the
simulator and the offline tools only inside the function of a command that needs them, so that
``mavvo run`` never loads them.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS = (
    ("mavvo.errors", "mavvo.options", "mavvo.types", "mavvo.jit", "mavvo"),
    ("mavvo.geometry",),
    ("mavvo.estimation",),
    ("mavvo.odometry",),
    ("mavvo.service",),
    ("mavvo.calibration",),
    ("mavvo.evaluation",),
    ("mavvo.fleet.engine",),  # the sweep engine: draws and the batch both run on it
    ("mavvo.sim", "mavvo.sim.world"),
    ("mavvo.sim.flight_controller",),
    ("mavvo.sim.scenarios",),
    ("mavvo.offline",),
    ("mavvo.fleet",),
    ("mavvo.cli", "mavvo.commands", "mavvo.__main__"),
    ("tools",),  # outside the package: the fault suite checks settings files through the command line
)
# What the command line loads only inside a command's function (start-up of ``mavvo run``).
LOADED_ON_DEMAND = ("mavvo.sim", "mavvo.offline", "mavvo.evaluation", "mavvo.fleet")
# Outside libraries with exactly one importer.
SOLE_IMPORTER = {
    "pymavlink": "mavvo.service.mavlink",
    "numba": "mavvo.jit",
    "filterpy": None,
}  # None: tests only (a reference)


@dataclass(frozen=True)
class Edge:
    importer: str
    imported: str
    line: int
    in_function: bool


def layer_of(module: str) -> int:
    """Index in LAYERS of the longest prefix that names ``module``'s layer."""
    best, rank = -1, -1
    for i, names in enumerate(LAYERS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > best:
                best, rank = len(name), i
    if rank < 0:
        raise AssertionError(f"{module}: in no layer; add it to LAYERS and docs/design.md")
    return rank


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(source: str, importer: str, package: bool) -> list[Edge]:
    """Every absolute or relative import in ``source``, with whether it sits inside a function."""
    tree = ast.parse(source)
    edges: list[Edge] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                edges.extend(Edge(importer, a.name, child.lineno, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                if child.level:
                    base = importer.split(".")[: len(importer.split(".")) - child.level + (1 if package else 0)]
                    mod = ".".join(base + ([child.module] if child.module else []))
                else:
                    mod = child.module or ""
                edges.append(Edge(importer, mod, child.lineno, in_function))
            visit(child, inner)

    visit(tree, False)
    return edges


def violations(edges: list[Edge]) -> list[str]:
    """What breaks the layering: an upward import, the simulator or the offline tools imported by the
    command line outside a command's function, a second importer of pymavlink or numba, or any
    importer of filterpy (a reference for the tests)."""
    out = []
    for e in edges:
        top = e.imported.split(".")[0]
        if top in SOLE_IMPORTER:
            if e.importer != SOLE_IMPORTER[top]:
                who = SOLE_IMPORTER[top] or "the tests"
                out.append(f"{e.importer}:{e.line} imports {top}; only {who} may")
            continue
        if top not in ("mavvo", "tools"):
            continue
        if layer_of(e.imported) > layer_of(e.importer):
            out.append(f"{e.importer}:{e.line} imports {e.imported}, a higher layer")
            continue
        on_demand = any(e.imported == p or e.imported.startswith(p + ".") for p in LOADED_ON_DEMAND)
        if on_demand and e.importer.startswith(("mavvo.commands", "mavvo.cli")) and not e.in_function:
            out.append(
                f"{e.importer}:{e.line} imports {e.imported}: the command line loads it only inside a command's function"
            )
    return out


def all_modules() -> dict[str, Path]:
    paths = sorted((ROOT / "mavvo").rglob("*.py")) + sorted((ROOT / "tools").rglob("*.py"))
    return {module_name(p): p for p in paths}


def all_edges() -> list[Edge]:
    return [
        e
        for name, p in all_modules().items()
        for e in imports_of(p.read_text(encoding="utf-8"), name, p.name == "__init__.py")
    ]


def test_every_import_points_down() -> None:
    assert violations(all_edges()) == []


def test_no_import_cycles_among_modules() -> None:
    modules = all_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for e in all_edges():
        if not e.in_function and e.imported in modules and e.imported != e.importer:
            graph[e.importer].add(e.imported)
    # A package's __init__ importing its own submodules is not a cycle of the layering.
    for m in graph:
        graph[m] = {d for d in graph[m] if not d.startswith(m + ".")}
    done: set[str] = set()

    def visit(m: str, stack: list[str]) -> None:
        if m in stack:
            raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(m) :] + [m]))
        if m in done:
            return
        for d in sorted(graph[m]):
            visit(d, stack + [m])
        done.add(m)

    for m in sorted(graph):
        visit(m, [])


def test_every_module_says_its_job_in_its_first_docstring_line() -> None:
    missing = []
    for name, p in all_modules().items():
        doc = ast.get_docstring(ast.parse(p.read_text(encoding="utf-8")))
        if not doc or not doc.splitlines()[0].strip():
            missing.append(name)
    assert missing == []


@pytest.mark.parametrize(
    "importer, source, package, expected",
    [
        ("mavvo.geometry.frames", "from mavvo.odometry.filter import wrap_angle\n", False, "a higher layer"),
        ("mavvo.service.daemon", "import mavvo.sim.world.scene\n", False, "a higher layer"),
        ("mavvo.sim.world.camera", "from mavvo.offline.driver import replay\n", False, "a higher layer"),
        ("mavvo.offline.driver", "from mavvo.cli import main\n", False, "a higher layer"),
        ("mavvo.commands.run", "from mavvo.sim.world.camera import x\n", False, "only inside a command's function"),
        ("mavvo.commands.replay", "from mavvo.offline import driver\n", False, "only inside a command's function"),
        ("mavvo.sim.world.camera", "from pymavlink import mavutil\n", False, "only mavvo.service.mavlink may"),
        ("mavvo.odometry.filter", "import filterpy.kalman\n", False, "only the tests may"),
        ("mavvo.geometry.essential", "from ..odometry import pipeline\n", False, "a higher layer"),
        ("mavvo.odometry", "from .pipeline import Odometry\nfrom ..service import daemon\n", True, "a higher layer"),
        ("mavvo.cli", "import tools.faults.suite\n", False, "a higher layer"),
    ],
)
def test_the_checker_finds_each_kind_of_violation(importer: str, source: str, package: bool, expected: str) -> None:
    found = violations(imports_of(source, importer, package))
    assert len(found) == 1 and expected in found[0]


def test_the_checker_allows_what_the_layering_allows() -> None:
    allowed = [
        ("mavvo.commands.sim", "def main():\n    from mavvo.sim.scenarios.loader import load_scenario\n", False),
        (
            "mavvo.offline.driver",
            "from mavvo.service.daemon import Daemon\nfrom mavvo.sim.world.clock import LockstepClock\n",
            False,
        ),
        (
            "mavvo.odometry.pipeline",
            "from mavvo.geometry.frames import R_lvl_cam\nfrom mavvo.types import PairedFrame\n",
            False,
        ),
        ("tools.faults.suite", "from mavvo.cli import main\n", False),
    ]
    for importer, source, package in allowed:
        assert violations(imports_of(source, importer, package)) == []


def test_only_mavvo_is_installed() -> None:
    """``pip install .`` installs the package ``mavvo`` and nothing beside it (no top-level ``sim``,
    no ``tools``): the packages setuptools finds with pyproject.toml's ``include``."""
    import re

    from setuptools import find_packages

    found = re.search(r"^include = \[(.*)\]$", (ROOT / "pyproject.toml").read_text(encoding="utf-8"), re.M)
    assert found is not None, "pyproject.toml: [tool.setuptools.packages.find] include not found"
    patterns = [p.strip().strip('"') for p in found.group(1).split(",")]
    packages = find_packages(where=str(ROOT), include=patterns)
    assert "mavvo" in packages and "mavvo.sim.scenarios" in packages and "mavvo.offline" in packages
    assert [p for p in packages if p.split(".")[0] != "mavvo"] == []


# What an import of the package needs from outside, by import name -> the distribution pyproject.toml
# must list. PyGObject (gi) and Picamera2 come from the distribution and are imported only by the camera
# source that needs them, which says what to install when they are missing.
DISTRIBUTION_OF = {
    "numpy": "numpy",
    "cv2": "opencv-python-headless",
    "pymavlink": "pymavlink",
    "serial": "pyserial",
    "yaml": "pyyaml",
    "pyulog": "pyulog",
    "numba": "numba",
    "scipy": "scipy",
    "matplotlib": "matplotlib",
}
FROM_THE_SYSTEM = {"gi", "picamera2"}
# Outside libraries of an optional extra: imported only inside functions, which say what to install.
IN_AN_EXTRA = {"distributed": "fleet", "dask": "fleet"}


def test_every_outside_import_of_the_package_is_a_declared_dependency() -> None:
    """An installed copy (no test or bench extras) runs every command: each library the package imports
    is in [project].dependencies (matplotlib was only in an extra, and `mavvo sim` ended in an error)."""
    import re
    import sys

    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    block = re.search(r"^dependencies = \[(.*?)^\]", text, re.M | re.S)
    assert block is not None, "pyproject.toml: [project] dependencies not found"
    declared = set(re.findall(r'^\s*"([A-Za-z0-9_.-]+)', block.group(1), re.M))
    outside = set()
    for name, path in all_modules().items():
        if not name.startswith("mavvo"):
            continue
        for e in imports_of(path.read_text(encoding="utf-8"), name, path.name == "__init__.py"):
            top = e.imported.split(".")[0]
            if top in IN_AN_EXTRA:
                extra = re.search(rf"^{IN_AN_EXTRA[top]} = \[(.*?)\]", text, re.M)
                assert extra is not None and "distributed" in extra.group(1), (
                    f"pyproject.toml: no {IN_AN_EXTRA[top]} extra"
                )
                assert e.in_function, f"{name}:{e.line}: {top} (an extra) imported at module level"
            elif top and top != "mavvo" and top not in sys.stdlib_module_names and top not in FROM_THE_SYSTEM:
                outside.add(top)
    unknown = sorted(outside - DISTRIBUTION_OF.keys())
    assert unknown == [], f"imported by mavvo, not in DISTRIBUTION_OF: {unknown}"
    assert sorted(m for m in outside if DISTRIBUTION_OF[m] not in declared) == []
