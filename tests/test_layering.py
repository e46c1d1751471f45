"""The import graph follows design.md §2: walks every module's imports (module level and inside
functions alike) and fails on a cycle or a forbidden arrow."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("hydo_cli", "models", "sim", "robot")
CONTRACT = {"sim.contract", "sim.primitive", "sim.atomic"}
FEASIBILITY = ("feasible_points", "feasibility_mask", "within_walls", "start_clear", "plans_inside")
COMMANDS = {
    "hydo_cli.train",
    "hydo_cli.evaluate",
    "hydo_cli.export",
    "hydo_cli.deploy",
    "hydo_cli.plot",
    "hydo_cli.sweep",
    "hydo_cli.review",
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imported_names(path: Path, mod: str) -> set[str]:
    """Every module named by an import in the file (``from a import b`` gives ``a`` and ``a.b``)."""
    names = set()
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(up + ([node.module] if node.module else []))
            names.add(base)
            names |= {f"{base}.{a.name}" for a in node.names}
    return names


MODULES = {module_name(p): p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")}
RAW = {m: imported_names(p, m) for m, p in MODULES.items()}
INITS = {m for m, p in MODULES.items() if p.name == "__init__.py"}
GRAPH = {m: {d for d in RAW[m] if d in MODULES and d != m} for m in MODULES}


def reachable(start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for d in GRAPH[todo.pop()] - INITS:
            if d not in seen:
                seen.add(d)
                todo.append(d)
    return seen


def test_the_walker_sees_the_packages():
    assert {"hydo_cli.main", "models.algos", "sim.env", "robot.loop"} <= set(MODULES)
    assert "models.encoder" in GRAPH["models.algos"] and "sim.contract" in GRAPH["robot.onnx_policy"]


def test_no_import_cycles():
    # a package's __init__ importing its own submodules is not a design cycle: __init__s are left out
    cycles = sorted(m for m in GRAPH if MODULES[m].name != "__init__.py" and m in reachable(m))
    assert cycles == []


def test_models_is_tensors_in_tensors_out():
    bad = []
    for m in (m for m in MODULES if m.split(".")[0] == "models"):
        for d in GRAPH[m]:
            top = d.split(".")[0]
            if top in ("robot", "hydo_cli") or (top == "sim" and d not in CONTRACT and d != "sim"):
                bad.append(f"{m} -> {d}")
        tree = ast.parse(MODULES[m].read_text())
        used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)} | {
            n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
        }
        bad += [f"{m} computes feasibility ({name})" for name in FEASIBILITY if name in used]
    assert bad == []


def test_sim_and_robot_never_import_torch():
    bad = [
        m
        for m in MODULES
        if m.split(".")[0] in ("sim", "robot") and any(d.split(".")[0] == "torch" for d in RAW[m])
    ]
    assert bad == []


def test_contract_modules_are_light():
    for m in CONTRACT | {"sim"}:
        heavy = {
            d
            for d in {m} | reachable(m)
            for r in RAW[d]
            if r.split(".")[0] in ("mujoco", "gymnasium", "torch")
        }
        assert heavy == set(), f"{m} reaches {heavy}"


def test_command_modules_do_not_import_each_other():
    bad = [f"{m} -> {d}" for m in COMMANDS for d in GRAPH[m] if d in COMMANDS]
    assert bad == []
    bench = [p.name for p in (ROOT / "bench").glob("*.py") if imported_names(p, "bench") & COMMANDS]
    assert bench == []


def test_real_arm_path_never_loads_the_renderer():
    for m in ("robot.perception", "robot.loop", "robot.panda", "robot.fr3"):
        assert "sim.render" not in reachable(m) | {m}, m


def test_no_test_doubles_in_the_package():
    assert [str(p) for pkg in PACKAGES for p in (ROOT / pkg).rglob("*fake*.py")] == []


@pytest.mark.parametrize(
    "code",
    [
        "import sim, sim.contract, sim.primitive, sim.atomic",
        "import hydo_cli.main",  # the CLI starts without torch or mujoco; deploy never needs torch
    ],
)
def test_light_imports_at_run_time(code):
    check = f"{code}; import sys; print(sorted({{'torch', 'mujoco', 'gymnasium'}} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", check], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
