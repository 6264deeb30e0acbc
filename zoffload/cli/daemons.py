"""The daemons' command lines: ``zoffload-robot``, ``zoffload-edge`` (also ``zoffload robot|edge``)
and ``zoffload router``. Their flags are built from the settings models (``zoffload.cli.flags``):
every setting is a flag, ``--key-name`` or ``--section.key-name``, with the help and default its
field declares; settings come from defaults < ``--settings FILE`` (YAML) < ``ZOFFLOAD_ROBOT__*`` /
``ZOFFLOAD_EDGE__*`` variables < flags.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel

from zoffload.cli.flags import Spelling, add_settings_flags, flag_values, summary
from zoffload.runtime.config import EdgeSettings, RobotSettings, ZenohSettings
from zoffload.runtime.errors import ExitCode
from zoffload.runtime.lifecycle import StopSignal
from zoffload.runtime.loading import EDGE_ENV, ROBOT_ENV, load_settings

log = logging.getLogger("zoffload")

# Flags are built from the settings models (zoffload.cli.flags): --key-name, --section.key-name.
# These tables only keep the spellings the flags have always had. The session flags are the zenoh
# examples' (-m -e -l -c --cfg); --no-multicast-scouting and --no-shm are derived from the "on" forms.
SESSION_SPELLINGS: dict[str, Spelling] = {
    "zenoh.mode": Spelling(("-m", "--mode")),
    "zenoh.connect": Spelling(("-e", "--connect"), "ENDPOINT"),
    "zenoh.listen": Spelling(("-l", "--listen"), "ENDPOINT"),
    "zenoh.multicast_scouting": Spelling(("--multicast-scouting",)),
    "zenoh.shared_memory": Spelling(("--shm",)),
    "zenoh.config_file": Spelling(("-c", "--config"), "FILE"),
    "zenoh.cfg": Spelling(("--cfg",), "KEY:VALUE"),
    "zenoh.tls_ca": Spelling(("--tls-ca",), "FILE"),
    "zenoh.tls_cert": Spelling(("--tls-cert",), "FILE"),
    "zenoh.tls_key": Spelling(("--tls-key",), "FILE"),
    "zenoh.user": Spelling(("--user",), "NAME"),
    "zenoh.password_file": Spelling(("--password-file",), "FILE"),
}
ROBOT_SPELLINGS: dict[str, Spelling] = {
    **SESSION_SPELLINGS,
    "rate_hz": Spelling(("--rate",), "HZ"),
    "voxel_range": Spelling(("--voxel-range",), ("LOW", "HIGH")),
    "out_dir": Spelling(("--out",), "DIR"),
}
EDGE_SPELLINGS: dict[str, Spelling] = {
    **SESSION_SPELLINGS,
    "mapper.enabled": Spelling(("--mapping",)),
    "detector.enabled": Spelling(("--detector",)),
}


def add_session_arguments(p: argparse.ArgumentParser) -> None:
    add_settings_flags(p, ZenohSettings, SESSION_SPELLINGS, prefix="zenoh", title="zenoh session")


def session_flags(a: argparse.Namespace) -> dict[str, Any]:
    """The Zenoh session settings given as flags (for ``ZenohSettings``)."""
    return flag_values(a, ZenohSettings, "zenoh")


class _HelpFormatter(argparse.HelpFormatter):
    """A wider flag column: most generated flags then keep their help on the same line."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=34)


def _daemon_parser(p: argparse.ArgumentParser, model: type[BaseModel], spellings: dict[str, Spelling],
                   env_prefix: str, example: str) -> None:
    p.description = p.description or summary(model)
    p.usage = "%(prog)s [--settings FILE] [flags]"  # the generated one would list every flag
    p.formatter_class = _HelpFormatter
    p.epilog = (
        "Each setting is, in rising precedence: its default (shown above), its key in --settings FILE "
        f"(YAML, sections nested), the environment variable {env_prefix}KEY or {env_prefix}SECTION__KEY "
        f"(e.g. {example}; lists in YAML: {env_prefix}ZENOH__CONNECT=[tcp/10.0.0.2:7447]; null unsets), "
        "then its flag. Unknown keys and variables are errors."
    )
    p.add_argument("--settings", metavar="FILE",
                   help="YAML settings file: the settings' keys (as in a run's *_config.yaml: rate_hz, "
                   "out_dir, fleet: {attach: ...}), sections nested")
    p.add_argument("--log-level", default=None, metavar="LEVEL",
                   help="DEBUG, INFO, WARNING (env ZOFFLOAD_LOG)")
    program = model.__name__.removesuffix("Settings").lower()
    add_settings_flags(p, model, spellings, title=f"{program} settings")


def robot_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="zoffload-robot")
    _daemon_parser(p, RobotSettings, ROBOT_SPELLINGS, ROBOT_ENV, f"{ROBOT_ENV}PERCEPTION__STRATEGY=edge")
    return p


def edge_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="zoffload-edge")
    _daemon_parser(p, EdgeSettings, EDGE_SPELLINGS, EDGE_ENV, f"{EDGE_ENV}MAPPER__QUEUE=4")
    from zoffload.cli.view import add_view_flags  # here: cli.view imports this module

    add_view_flags(p, "view-")
    return p


def robot_settings(a: argparse.Namespace, environ: Mapping[str, str] | None = None) -> RobotSettings:
    """Defaults < ``--settings`` file < ``ZOFFLOAD_ROBOT__*`` (``environ``, else os.environ) < flags."""
    return load_settings(RobotSettings, a.settings, flag_values(a, RobotSettings), ROBOT_ENV, environ)


def edge_settings(a: argparse.Namespace, environ: Mapping[str, str] | None = None) -> EdgeSettings:
    """Defaults < ``--settings`` file < ``ZOFFLOAD_EDGE__*`` (``environ``, else os.environ) < flags."""
    return load_settings(EdgeSettings, a.settings, flag_values(a, EdgeSettings), EDGE_ENV, environ)


def run_robot(a: argparse.Namespace) -> int:
    from zoffload.robot.server import run

    metrics = run(robot_settings(a), StopSignal().install())
    failed = {name: m["source_failed"] for name, m in metrics.items() if m.get("source_failed")}
    for name, why in failed.items():  # the results are written; the run ended short of its data
        log.error("data error: the %s source failed and ended the run early: %s", name, why)
    return ExitCode.DATA if failed else ExitCode.OK


def run_edge(a: argparse.Namespace) -> int:
    from zoffload.edge.server import run

    if getattr(a, "view", False):
        from zoffload.cli.view import run_edge_with_view

        return run_edge_with_view(a, edge_settings(a))
    run(edge_settings(a), StopSignal().install())
    return ExitCode.OK


def run_router(a: argparse.Namespace) -> int:
    from zoffload.runtime.router import run

    z = session_flags(a)
    z["mode"] = "router"
    run(load_settings(RobotSettings, None, {"zenoh": z}).zenoh, StopSignal().install())
    return ExitCode.OK


def add_robot(sub: Any) -> None:
    r = sub.add_parser("robot", help="the robot daemon (same as zoffload-robot)")
    robot_parser(r).set_defaults(func=run_robot)


def add_edge(sub: Any) -> None:
    e = sub.add_parser("edge", help="the edge daemon (same as zoffload-edge)")
    edge_parser(e).set_defaults(func=run_edge)


def add_router(sub: Any) -> None:
    rt = sub.add_parser("router", help="a Zenoh router (zenoh-python in router mode)")
    add_session_arguments(rt)
    rt.add_argument("--log-level", default=None)
    rt.set_defaults(func=run_router)


