"""package.xml declares every third-party module the package and its tests import, under
its rosdep key, so `rosdep install --from-paths` installs what the code needs; each key is
rosdistro's or defined in rosdep/gscan_ros.yaml. setup.py lists the same Python (non-ROS)
ones for pip: run-time in install_requires, test-only in the `test` extra."""
import ast
import re
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
# Keys rosdep resolves from rosdistro itself, as checked in ros/rosdistro (2026-08-22):
# the ROS 2 Jazzy packages of jazzy/distribution.yaml, which come from ROS, not from pip...
ROS_PACKAGES = {"actionlib_msgs", "ament_index_python", "builtin_interfaces", "diagnostic_msgs", "launch", "launch_ros",
                "rcl_interfaces", "rclpy", "ros2launch", "sensor_msgs", "std_msgs", "std_srvs"}
# ...and the system keys of rosdep/python.yaml. python3-nltk, -zstandard, -lz4, wordnet-base
# and any key for mcap are not there (nor in rosdep/base.yaml): rosdep/gscan_ros.yaml has them.
ROSDISTRO_KEYS = ROS_PACKAGES | {
    "mcap-ros2-support", "python3-hypothesis", "python3-matplotlib", "python3-numpy", "python3-pil",
    "python3-pytest", "python3-rosbags-pip", "python3-setuptools", "python3-torch", "python3-tqdm", "python3-yaml",
    "python3-pip", "python3-wheel",  # rosdep/python.yaml, checked 2026-12-07
}
# Top-level import name -> rosdep key (a ROS package is its own key).
ROSDEP_KEYS = {package: package for package in ROS_PACKAGES} | {
    "PIL": "python3-pil",
    "hypothesis": "python3-hypothesis",
    "lz4": "python3-lz4",
    "matplotlib": "python3-matplotlib",
    "mcap": "python3-mcap-pip",
    "mcap_ros2": "mcap-ros2-support",
    "nltk": "python3-nltk",
    "numpy": "python3-numpy",
    "pytest": "python3-pytest",
    "rosbags": "python3-rosbags-pip",
    "setuptools": "python3-setuptools",
    "torch": "python3-torch",
    "tqdm": "python3-tqdm",
    "yaml": "python3-yaml",
    "zstandard": "python3-zstandard",
}
ROSDEP_FILE = REPO / "rosdep" / "gscan_ros.yaml"
RUNTIME_SOURCES = ("gscan_ros", "msg_adapters", "launch", "scripts")
OWN = {"gscan_ros", "msg_adapters"}
RUNTIME = ("exec_depend", "depend")
# Import name -> pip distribution where they differ.
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


DEPENDENCY_TAGS = ("depend", "build_depend", "buildtool_depend", "build_export_depend", "exec_depend",
                   "test_depend", "doc_depend")


def declared(*tags: str) -> set[str]:
    root = ET.parse(REPO / "package.xml").getroot()
    return {element.text.strip() for tag in tags for element in root.iter(tag)}


def rosdep_file() -> dict:
    return yaml.safe_load(ROSDEP_FILE.read_text())


@pytest.mark.parametrize("module", sorted(imported_modules(*RUNTIME_SOURCES)))
def test_every_runtime_import_is_an_exec_depend(module):
    assert module in ROSDEP_KEYS, f"{module}: add its rosdep key to ROSDEP_KEYS and package.xml"
    assert ROSDEP_KEYS[module] in declared(*RUNTIME), f"package.xml lacks <exec_depend>{ROSDEP_KEYS[module]}"


@pytest.mark.parametrize("module", sorted(imported_modules("tests") - imported_modules(*RUNTIME_SOURCES)))
def test_every_test_only_import_is_a_test_depend(module):
    assert module in ROSDEP_KEYS, f"{module}: add its rosdep key to ROSDEP_KEYS and package.xml"
    assert ROSDEP_KEYS[module] in declared("test_depend"), f"package.xml lacks <test_depend>{ROSDEP_KEYS[module]}"


def test_a_shipped_launch_file_brings_ros2_launch():
    """`ros2 launch gscan_ros gscan.launch.py` needs the `launch` verb of the ros2 CLI (ros2launch)."""
    assert list((REPO / "launch").glob("*.launch.py"))
    assert "ros2launch" in declared(*RUNTIME)


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
    return {DISTRIBUTIONS.get(m, m).lower() for m in modules if m not in ROS_PACKAGES}


def test_setup_py_requires_the_python_imports_and_keeps_test_only_ones_in_the_test_extra():
    runtime, test = setup_requirements()
    runtime_imports = imported_modules(*RUNTIME_SOURCES)
    assert runtime == pip_names(runtime_imports)
    assert test == pip_names(imported_modules("tests") - runtime_imports)


@pytest.mark.parametrize("key", sorted(declared(*DEPENDENCY_TAGS)))
def test_every_rosdep_key_is_rosdistros_or_defined_in_the_rosdep_file(key):
    assert key in ROSDISTRO_KEYS or key in rosdep_file(), f"{key}: not a rosdistro key; define it in {ROSDEP_FILE.name}"


def test_rosdep_file_defines_only_keys_that_package_xml_uses_and_rosdistro_lacks():
    defined = set(rosdep_file())
    assert defined <= declared(*DEPENDENCY_TAGS)
    assert not defined & ROSDISTRO_KEYS  # rosdistro defines these: its rules win (docs/ros.md)


def test_rosdep_file_has_the_rosdep_structure():
    """REP 111 rules: apt package lists for Debian and Ubuntu, pip (`{pip: {packages: [...]}}`)
    for every other system (`'*'`); the pip packages are setup.py's requirements."""
    runtime, test = setup_requirements()
    for key, rules in rosdep_file().items():
        assert isinstance(rules, dict) and rules and set(rules) <= {"debian", "ubuntu", "*"}, key
        for os_name, rule in rules.items():
            if os_name == "*":
                assert list(rule) == ["pip"] and list(rule["pip"]) == ["packages"], key
                packages = rule["pip"]["packages"]
                assert {p.lower() for p in packages} <= runtime | test, key
            else:
                packages = rule
            assert isinstance(packages, list) and packages and all(isinstance(p, str) for p in packages), key
