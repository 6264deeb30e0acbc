"""Command line: ``zoffload demo | robot | edge | router``, ``zoffload-robot``, ``zoffload-edge``.

``main()`` only parses arguments and calls the ``run(settings)`` functions, which are also the
Python API. Every program takes the Zenoh session flags of the zenoh examples
(``-m -e -l -c --no-multicast-scouting --cfg``) plus ``--no-shm``; program settings come from
``--settings FILE`` (YAML), then ``ZOFFLOAD_ROBOT__*`` / ``ZOFFLOAD_EDGE__*`` variables, then flags.
The daemons' flags are built from the settings models (``zoffload.cli.flags``): every setting is a
flag, ``--key-name`` or ``--section.key-name``, with the help and default its field declares.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence

from zoffload import __version__
from zoffload.cli import daemons, hardening, lab, view
from zoffload.cli.daemons import edge_parser, robot_parser, run_edge, run_robot
from zoffload.detect.models import ModelError
from zoffload.runtime.errors import ConfigError, ExitCode, ZenohSessionError
from zoffload.runtime.lifecycle import setup_logging
from zoffload.sources.base import ScanSourceError

log = logging.getLogger("zoffload")


def _guard(fn: Callable[[argparse.Namespace], int], a: argparse.Namespace) -> int:
    """Run a command, turning the errors a user can cause into a message and a named exit code."""
    setup_logging(getattr(a, "log_level", None))
    try:
        return int(fn(a))
    except ConfigError as exc:
        log.error("configuration error: %s", exc)
        return ExitCode.CONFIG
    except ScanSourceError as exc:
        log.error("data error: %s", exc)
        return ExitCode.DATA
    except ModelError as exc:
        log.error("model error: %s", exc)
        return ExitCode.DATA
    except ZenohSessionError as exc:
        log.error("%s", exc)
        return ExitCode.ZENOH
    except KeyboardInterrupt:
        return ExitCode.INTERRUPTED
    except Exception:
        log.exception("unexpected error")
        return ExitCode.FAILURE


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="zoffload",
        description="Offload a robot's LiDAR mapping to an edge computer over Zenoh, and keep working "
        "when the link degrades. Start with: zoffload demo",
    )
    p.add_argument("--version", action="version", version=f"zoffload {__version__}")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (lab.add_demo, daemons.add_robot, daemons.add_edge, lab.add_experiment, lab.add_report,
                lab.add_train_policy, lab.add_link, daemons.add_router, view.add_view, hardening.add_certs,
                hardening.add_soak):
        add(sub)
    return exact_flags(p)


def exact_flags(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Turn off argparse's prefix matching, here and in every sub-command: ``--mapper.queu 7``
    was taken as ``--mapper.queue`` (a typo silently accepted, where a wrong key in a file or a
    variable is an error)."""
    p.allow_abbrev = False
    for action in p._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in set(action.choices.values()):
                exact_flags(child)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return _guard(args.func, args)


def robot_main(argv: Sequence[str] | None = None) -> int:
    args = exact_flags(robot_parser()).parse_args(argv)
    return _guard(run_robot, args)


def edge_main(argv: Sequence[str] | None = None) -> int:
    args = exact_flags(edge_parser()).parse_args(argv)
    return _guard(run_edge, args)


if __name__ == "__main__":
    sys.exit(main())
