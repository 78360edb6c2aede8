"""The core never imports ROS itself: rclpy and message packages only in nodes/ and msg_adapters/
(docs/architecture.md); the bag code reaches ROS messages through msg_adapters."""
import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "gscan_ros"
CORE = ("world", "language", "data", "model", "training")
ROS = {"rclpy", "std_msgs", "sensor_msgs", "std_srvs", "rcl_interfaces", "builtin_interfaces"}


def ros_imports(path: Path) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
            [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
        found += [n for n in names if n.split(".")[0] in ROS]
    return found


def test_core_modules_and_the_interface_table_import_no_ros_package():
    files = [f for layer in CORE for f in sorted((PACKAGE / layer).rglob("*.py"))] + [PACKAGE / "interface.py"]
    assert len(files) > 20
    offenders = {str(f.relative_to(PACKAGE)): ros_imports(f) for f in files if ros_imports(f)}
    assert offenders == {}
