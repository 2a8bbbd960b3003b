"""Package boundaries follow deployment: a drone that runs only the policy installs no simulator, and
the simulator installs no torch. Measuring (uav_eval) may import the policy, the simulator and common code; nothing
imports measuring (train runs its `choose` as a program)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

PACKAGES = ("uav_common", "uav_sim", "uav_policy", "uav_trainer", "uav_bringup", "uav_eval")
PATHS = [str(ROOT / "src" / p) for p in PACKAGES]


def imported_after(module: str) -> set[str]:
    """The top-level modules loaded by importing `module` in a fresh interpreter."""
    listing = "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    code = f"import sys; sys.path[:0] = {PATHS!r}; import {module}; {listing}"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return set(r.stdout.split())


def test_the_policy_node_imports_no_simulator():
    loaded = imported_after("uav_policy.policy_node")
    assert "torch" in loaded  # it did import the network
    assert not {"pybullet", "uav_sim", "uav_trainer"} & loaded


@pytest.mark.parametrize("module", ["uav_sim.sim_node", "uav_sim.gym"])
def test_the_simulator_imports_no_torch(module):
    loaded = imported_after(module)
    assert "pybullet" in loaded
    assert not {"torch", "uav_policy", "uav_trainer"} & loaded


def test_package_manifests_declare_what_the_code_imports():
    """uav_policy and uav_sim depend on uav_common, never on each other."""
    policy = (ROOT / "src/uav_policy/package.xml").read_text()
    sim = (ROOT / "src/uav_sim/package.xml").read_text()
    assert "<exec_depend>uav_common</exec_depend>" in policy and "uav_sim" not in policy
    assert "<exec_depend>uav_common</exec_depend>" in sim and "uav_policy" not in sim


@pytest.mark.parametrize("module", ["uav_bringup.record", "uav_bringup.live_view", "uav_bringup.fly"])
def test_recording_and_watching_import_no_network_and_no_simulator(module):
    """A drone's companion computer records and serves its flight without torch or pybullet."""
    loaded = imported_after(module)
    assert "uav_common" in loaded
    assert not {"torch", "pybullet", "uav_sim", "uav_policy", "uav_trainer"} & loaded


@pytest.mark.parametrize(
    "module",
    ["uav_trainer.inprocess", "uav_trainer.trainer_node", "uav_trainer.distill", "uav_policy.rollout"],
)
def test_learning_imports_no_measuring(module):
    loaded = imported_after(module)
    assert "uav_eval" not in loaded and "torch" in loaded


def test_comparing_tables_imports_no_network():
    """compare_models reads results.csv files: it starts in a fraction of a second, without torch."""
    loaded = imported_after("uav_eval.compare_models")
    assert "numpy" in loaded and not {"torch", "pybullet", "rclpy"} & loaded


def test_no_package_but_uav_eval_imports_uav_eval_anywhere_in_its_code():
    """Lazy imports inside functions included: the arrows point one way."""
    pattern = re.compile(r"^\s*(from|import)\s+uav_eval\b", re.MULTILINE)
    offenders = [
        str(f.relative_to(ROOT))
        for pkg in PACKAGES
        if pkg != "uav_eval"
        for f in (ROOT / "src" / pkg).rglob("*.py")
        if pattern.search(f.read_text())
    ]
    assert offenders == []
    evaluate = (ROOT / "src/uav_eval/uav_eval/evaluate.py").read_text()
    assert pattern.search("from uav_eval.tables import pool") and "from .tables import" in evaluate  # the check can match


def test_the_training_launcher_and_the_run_settings_import_no_network():
    """`train` parses and checks its settings before anything learns: it starts (and refuses bad flags) without
    torch, whose import is most of a second-and-a-half start."""
    for module in ("uav_trainer.train", "uav_trainer.training_config", "uav_policy.net_config"):
        loaded = imported_after(module)
        assert "uav_policy" in loaded and not {"torch", "pybullet", "uav_eval"} & loaded, module


def module_imports(root=ROOT / "src") -> dict[str, set[str]]:
    """Each of the stack's modules -> the stack's modules it imports anywhere in its code (at the top or inside a
    function), `if TYPE_CHECKING:` blocks aside (annotations only)."""
    import ast

    graph = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg / pkg).glob("*.py")):
            name = f"{pkg}.{path.stem}"
            tree = ast.parse(path.read_text())
            skip = {
                id(n)
                for node in ast.walk(tree)
                if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
                for n in ast.walk(node)
            }
            found = set()
            for node in ast.walk(tree):
                if id(node) in skip:
                    continue
                if isinstance(node, ast.Import):
                    found |= {a.name for a in node.names}
                elif isinstance(node, ast.ImportFrom):
                    base = f"{pkg}.{node.module}" if node.level else node.module or ""
                    if node.level and not node.module:  # from . import x
                        found |= {f"{pkg}.{a.name}" for a in node.names}
                    else:
                        found.add(base)
                        found |= {f"{base}.{a.name}" for a in node.names}
            graph[name] = found
    return {m: {i for i in found if i in graph and i != m} for m, found in graph.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of `graph` (one path each), found by depth-first search."""
    out, state = [], {}

    def visit(m, path):
        state[m] = "open"
        for n in sorted(graph[m]):
            if state.get(n) == "open":
                out.append(path[path.index(n) :] + [n])
            elif n not in state:
                visit(n, [*path, n])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    return out


def test_no_module_of_the_stack_imports_itself_through_another():
    """No import circle, however deep or late the import: each module can be read on its own terms."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == [["a", "b", "c", "a"]]  # the check can fail
    graph = module_imports()
    assert len(graph) > 80 and "uav_policy.masking" in graph["uav_policy.insight"]
    assert cycles(graph) == []


def long_functions(root=ROOT / "src", max_parameters: int = 10, max_lines: int = 120) -> list[str]:
    """'path:function (n parameters, m lines)' for each function with more parameters or lines than allowed."""
    import ast

    out = []
    for path in sorted(root.glob("uav_*/uav_*/*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                a = node.args
                bound = bool(a.args) and a.args[0].arg in ("self", "cls")
                n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) - bound
                lines = node.end_lineno - node.lineno + 1
                if n > max_parameters or lines > max_lines:
                    out.append(f"{path.relative_to(root)}:{node.name} ({n} parameters, {lines} lines)")
    return out


def test_no_function_takes_more_than_ten_parameters_or_runs_over_120_lines(tmp_path):
    """Settings that travel together are one object (uav_eval.flights.FlightSpec, distill's Schedule); a long main is
    split into its steps."""
    (tmp_path / "uav_x" / "uav_x").mkdir(parents=True)
    (tmp_path / "uav_x" / "uav_x" / "m.py").write_text("def f(a, b, c, d, e, f, g, h, i, j, k):\n    pass\n")
    assert long_functions(tmp_path) == ["uav_x/uav_x/m.py:f (11 parameters, 2 lines)"]  # the check can fail
    assert long_functions() == []


def ros_packages_imported(pkg: str) -> set[str]:
    """The ROS packages (those with a package.xml in the venv's prefix or the workspace) `pkg`'s modules import."""
    import ast

    names = set()
    for path in (ROOT / "src" / pkg / pkg).glob("*.py"):
        tree = ast.parse(path.read_text())
        typing = {
            id(n) for t in ast.walk(tree) if isinstance(t, ast.If) and "TYPE_CHECKING" in ast.unparse(t.test) for n in ast.walk(t)
        }
        for node in ast.walk(tree):
            if id(node) in typing:
                continue
            if isinstance(node, ast.Import):
                names |= {a.name.split(".")[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
                names.add(node.module.split(".")[0])
    prefixes = (Path(sys.prefix) / "share", ROOT / "src")
    return {n for n in names - {pkg} if any((p / n / "package.xml").exists() for p in prefixes)}


def test_every_package_declares_the_ros_packages_it_imports():
    """colcon orders the build and a ROS install resolves dependencies by package.xml: what a package imports is in it."""
    assert {"rclpy", "uav_interfaces", "sensor_msgs"} <= ros_packages_imported("uav_trainer")  # the check sees them
    for pkg in PACKAGES:
        declared = set(re.findall(r"<(?:exec_)?depend>([\w]+)</", (ROOT / "src" / pkg / "package.xml").read_text()))
        missing = ros_packages_imported(pkg) - declared
        assert not missing, f"src/{pkg}/package.xml does not declare {sorted(missing)}"
