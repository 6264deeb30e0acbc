"""The package's layers and the one-way direction of imports between them.

    protocol, mapping, policy, detect, sources,  the core: pure computation and data
    ros2
        ^ runtime                                process plumbing: settings, sessions, monitors
            ^ robot, edge                        the two daemons (never each other)
                ^ lab                            demo, experiments, link emulator, evaluation
                    ^ cli                        argument parsing only

Every ``import`` of a ``zoffload`` module counts, also the lazy ones inside functions.
"""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "zoffload"
RANK = {"protocol": 0, "mapping": 0, "policy": 0, "detect": 0, "sources": 0, "ros2": 0, "runtime": 1,
        "robot": 2, "edge": 2, "lab": 3, "cli": 4}
# Within the core, the few directions allowed (a cycle there would make the layers meaningless)
CORE = {"policy": {"mapping"}, "mapping": {"protocol"}, "protocol": set(), "detect": set(),
        "sources": {"ros2"}, "ros2": set()}


def layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANK else "protocol"  # zoffload/__init__: bottom


def imports(source: str) -> list[str]:
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # ``from zoffload import wire`` names the module in the alias
            out += [f"zoffload.{a.name}" for a in node.names] if node.module == "zoffload" else [node.module]
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names]
    return [m for m in out if m == "zoffload" or m.startswith("zoffload.")]


def violations(modules: dict[str, str]) -> list[str]:
    """``module name -> source`` in, every wrong-way import out (as "a -> b (why)")."""
    bad = []
    for name, source in modules.items():
        src = layer(name)
        for target in imports(source):
            dst = layer(target)
            if dst == src or target == "zoffload":
                continue
            if RANK[dst] > RANK[src]:
                bad.append(f"{name} -> {target} ({src} may not import the higher {dst})")
            elif RANK[dst] == RANK[src] and not (src in CORE and dst in CORE[src]):
                bad.append(f"{name} -> {target} ({src} and {dst} are peers)")
    return sorted(set(bad))


def package_modules() -> dict[str, str]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        out[".".join(rel.parts)] = path.read_text()
    return out


def test_every_import_points_down_the_layers() -> None:
    modules = package_modules()
    assert len(modules) > 50 and {layer(m) for m in modules} == set(RANK)
    assert violations(modules) == []


def test_the_check_catches_wrong_way_and_peer_imports() -> None:
    lazy = "def f():\n    from zoffload.lab.runner import run_offload\n"
    assert violations({"zoffload.robot.scans": lazy}) == [
        "zoffload.robot.scans -> zoffload.lab.runner (robot may not import the higher lab)"]
    assert violations({"zoffload.protocol.wire": "import zoffload.runtime.config"})
    assert violations({"zoffload.robot.local": "from zoffload.edge import server"})  # peers
    assert violations({"zoffload.mapping.voxel": "from zoffload.policy.rate import LinkView"})
    assert violations({"zoffload.policy.rate": "from zoffload.mapping.voxel import voxel_downsample"}) == []
    assert violations({"zoffload.cli.main": "from zoffload.lab.demo import run"}) == []
