"""package.xml declares every third-party module the package and its tests import, under
its rosdep key, so `rosdep install --from-paths` installs what the code needs; setup.py
lists the same Python (non-ROS) ones for pip: run-time in install_requires, test-only in
the `test` extra."""
import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Top-level import name -> rosdep key (ROS packages are their own key).
ROSDEP_KEYS = {
    "PIL": "python3-pil",
    "ament_index_python": "ament_index_python",
    "builtin_interfaces": "builtin_interfaces",
    "hypothesis": "python3-hypothesis",
    "launch": "launch",
    "launch_ros": "launch_ros",
    "lz4": "python3-lz4",
    "matplotlib": "python3-matplotlib",
    "mcap": "python3-mcap-pip",
    "mcap_ros2": "python3-mcap-ros2-support-pip",
    "nltk": "python3-nltk",
    "numpy": "python3-numpy",
    "pytest": "python3-pytest",
    "rcl_interfaces": "rcl_interfaces",
    "rclpy": "rclpy",
    "rosbags": "python3-rosbags-pip",
    "sensor_msgs": "sensor_msgs",
    "setuptools": "python3-setuptools",
    "std_msgs": "std_msgs",
    "std_srvs": "std_srvs",
    "torch": "python3-torch",
    "tqdm": "python3-tqdm",
    "yaml": "python3-yaml",
    "zstandard": "python3-zstandard",
}
RUNTIME_SOURCES = ("gscan_ros", "msg_adapters", "launch", "scripts")
OWN = {"gscan_ros", "msg_adapters"}
RUNTIME = ("exec_depend", "depend")
# Import name -> pip distribution where they differ. ROS packages (rosdep key not python3-*)
# come from ROS, not from pip.
DISTRIBUTIONS = {"PIL": "pillow", "yaml": "pyyaml", "mcap_ros2": "mcap-ros2-support"}


def imported_modules(*roots: str) -> set[str]:
    """Top-level names of the absolute imports in the Python files under `roots` (scripts
    without a .py suffix included), less the standard library and this repo's own."""
    names: set[str] = set()
    for root in roots:
        top = REPO / root
        for path in [top] if top.is_file() else top.rglob("*"):
            if not path.is_file() or path.suffix not in (".py", "") or "__pycache__" in path.parts:
                continue
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.Import):
                    names |= {alias.name.split(".")[0] for alias in node.names}
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names.add(node.module.split(".")[0])
    local = {"tests"} | {p.stem for folder in ("tests", "bench") for p in (REPO / folder).glob("*.py")}
    return names - set(sys.stdlib_module_names) - OWN - local


def declared(*tags: str) -> set[str]:
    root = ET.parse(REPO / "package.xml").getroot()
    return {element.text.strip() for tag in tags for element in root.iter(tag)}


@pytest.mark.parametrize("module", sorted(imported_modules(*RUNTIME_SOURCES)))
def test_every_runtime_import_is_an_exec_depend(module):
    assert module in ROSDEP_KEYS, f"{module}: add its rosdep key to ROSDEP_KEYS and package.xml"
    assert ROSDEP_KEYS[module] in declared(*RUNTIME), f"package.xml lacks <exec_depend>{ROSDEP_KEYS[module]}"


@pytest.mark.parametrize("module", sorted(imported_modules("tests") - imported_modules(*RUNTIME_SOURCES)))
def test_every_test_only_import_is_a_test_depend(module):
    assert module in ROSDEP_KEYS, f"{module}: add its rosdep key to ROSDEP_KEYS and package.xml"
    assert ROSDEP_KEYS[module] in declared("test_depend"), f"package.xml lacks <test_depend>{ROSDEP_KEYS[module]}"


def test_build_and_data_dependencies():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.findtext("export/build_type") == "ament_python"
    assert {ROSDEP_KEYS[m] for m in imported_modules("setup.py")} <= declared("build_depend", "depend")
    assert "wordnet-base" in declared(*RUNTIME)  # the lexicon reads Debian's WordNet files


def setup_requirements() -> tuple[set[str], set[str]]:
    """setup.py's install_requires and extras_require['test'] (names without version specifiers)."""
    call = next(n for n in ast.walk(ast.parse((REPO / "setup.py").read_text()))
                if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "setup")
    wanted = ("install_requires", "extras_require")
    kwargs = {k.arg: ast.literal_eval(k.value) for k in call.keywords if k.arg in wanted}

    def names(requirements):
        return {re.split(r"[<>=!~\[; ]", r, maxsplit=1)[0].lower() for r in requirements}

    return names(kwargs["install_requires"]), names(kwargs["extras_require"]["test"])


def pip_names(modules: set[str]) -> set[str]:
    return {DISTRIBUTIONS.get(m, m).lower() for m in modules if ROSDEP_KEYS.get(m, "").startswith("python3-")}


def test_setup_py_requires_the_python_imports_and_keeps_test_only_ones_in_the_test_extra():
    runtime, test = setup_requirements()
    runtime_imports = imported_modules(*RUNTIME_SOURCES)
    assert runtime == pip_names(runtime_imports)
    assert test == pip_names(imported_modules("tests") - runtime_imports)
