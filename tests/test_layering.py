"""The layering of docs/architecture.md, checked on the import graph of the source: packages
import downwards only, no module takes part in an import cycle (imports inside functions
count), and only gscan_ros/nodes imports ROS. The last holds at run time too: with every
ROS package unimportable, the core imports and a bag is written and read back."""
import ast
import graphlib
from collections import defaultdict
from pathlib import Path

import pytest
from no_ros_support import is_ros, run_without_ros

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("gscan_ros", "msg_adapters")

# Every package and top-level module of the product, lowest layer first. A module may import
# from its own layer and the layers listed before it.
LAYERS = [
    {"gscan_ros", "gscan_ros.errors"},
    {"gscan_ros.user_files", "gscan_ros.outputs", "gscan_ros.interface", "gscan_ros.episode_status"},
    {"gscan_ros.world"},
    {"gscan_ros.language"},
    {"msg_adapters"},
    {"gscan_ros.data"},
    {"gscan_ros.model"},
    {"gscan_ros.runtime", "gscan_ros.analysis"},
    {"gscan_ros.training"},
    {"gscan_ros.experiments"},
    {"gscan_ros.nodes"},
    {"gscan_ros.cli"},
]
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}

def module_files() -> dict[str, Path]:
    files = {}
    for source in SOURCES:
        for path in sorted((ROOT / source).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            files[".".join(parts)] = path
    return files


def imported_names(module: str, path: Path, modules: set[str]) -> list[tuple[str, int]]:
    """Every module an import statement anywhere in the file loads, with its line: `from a
    import b` loads `a.b` where that is a module, else `a` (relative imports resolved)."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([node.module] if node.module else []))
            for alias in node.names:
                submodule = f"{base}.{alias.name}"
                found.append((submodule if submodule in modules else base, node.lineno))
    return found


def unit_of(module: str) -> str:
    """The layer unit a module belongs to: its subpackage of gscan_ros, or the module itself."""
    parts = module.split(".")
    if parts[0] == "msg_adapters":
        return "msg_adapters"
    if len(parts) > 1 and (ROOT / parts[0] / parts[1]).is_dir():
        return ".".join(parts[:2])
    return module


@pytest.fixture(scope="module")
def graph() -> dict[str, dict[str, int]]:
    """module -> {imported product module or ROS name: line}."""
    files = module_files()
    edges: dict[str, dict[str, int]] = defaultdict(dict)
    for module, path in files.items():
        for name, line in imported_names(module, path, set(files)):
            if name in files and name != module or is_ros(name):
                edges[module].setdefault(name, line)
    return {module: dict(edges[module]) for module in files}


def test_every_unit_has_a_layer(graph):
    units = {unit_of(module) for module in graph}
    assert units - RANK.keys() == set(), "add the new package or module to LAYERS and docs/architecture.md"
    assert len(graph) > 100


def test_packages_import_downwards_only(graph):
    upward = [f"{module} -> {name} (line {line})"
              for module, names in graph.items() for name, line in names.items()
              if not is_ros(name) and RANK[unit_of(name)] > RANK[unit_of(module)]]
    assert upward == []


def test_no_module_is_part_of_an_import_cycle(graph):
    product = {module: {name for name in names if not is_ros(name)} for module, names in graph.items()}
    try:
        graphlib.TopologicalSorter(product).prepare()
    except graphlib.CycleError as error:
        pytest.fail(f"import cycle: {' -> '.join(error.args[1])}")


def test_only_nodes_import_ros(graph):
    offenders = {module: sorted(name for name in names if is_ros(name))
                 for module, names in graph.items()
                 if not module.startswith("gscan_ros.nodes") and any(is_ros(name) for name in names)}
    assert offenders == {}


def test_the_check_sees_a_planted_upward_import_and_a_ros_import(tmp_path):
    planted = tmp_path / "gscan_ros" / "world" / "planted.py"
    planted.parent.mkdir(parents=True)
    planted.write_text("def f():\n    from gscan_ros.training import trainer\n    import rclpy\n")
    names = dict(imported_names("gscan_ros.world.planted", planted, set(module_files())))
    assert "gscan_ros.training.trainer" in names
    assert RANK[unit_of("gscan_ros.training.trainer")] > RANK[unit_of("gscan_ros.world.planted")]
    assert any(is_ros(name) for name in names)


def test_bench_imports_nothing_from_tests():
    offenders = [str(path.relative_to(ROOT)) for path in sorted((ROOT / "bench").rglob("*.py"))
                 if any(name.split(".")[0] == "tests" for name, _ in imported_names("bench", path, set()))]
    assert offenders == []


def test_the_core_runs_without_ros(tmp_path):
    """A machine without ROS imports every module below the nodes, and the command line
    generates bags, trains on them and replays them."""
    core = [m for m in module_files() if RANK[unit_of(m)] < RANK["gscan_ros.nodes"]]
    bags, run = tmp_path / "bags", tmp_path / "run"
    done = run_without_ros(f"""
        import importlib
        for module in {core!r}:
            importlib.import_module(module)
        from gscan_ros.cli import main
        assert main(["generate", "--out", {str(bags)!r}, "--format", "mcap", "--examples", "40", "--seed", "0",
                     "--workers", "1", "--quiet"]) == 0
        assert main(["train", "--data", {str(bags)!r}, "--out", {str(run)!r}, "--quiet", "--set", "batch_size=4",
                     "--set", "max_updates=2", "--set", "validate_every=2", "--set", "threads=1",
                     "--set", "dev_split=train", "--set", "max_dev_examples=4", "--set", "lexicon=none"]) == 0
        assert main(["replay", {str(bags / "train")!r}, "--checkpoint", {str(run / "model.pt")!r},
                     "--max-episodes", "3"]) == 0
        assert not any(name.split(".")[0] in ("rclpy", "std_msgs", "sensor_msgs") for name in sys.modules)
        print("no ROS loaded")
    """)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "replayed 3 episodes" in done.stdout and done.stdout.endswith("no ROS loaded\n")
