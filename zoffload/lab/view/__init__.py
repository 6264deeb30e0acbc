"""The live view: a Rerun viewer, served to the browser, of what robots and edges say on Zenoh.

An observing client (it sends nothing but map queries): ``feed.py`` subscribes to a session and
hands decoded messages, on one thread, to ``recording.py``, the pure layer that decides which
Rerun entity each becomes; ``serve.py`` serves that recording (gRPC + the bundled web viewer) and
saves it (.rrd); ``edge.py`` runs the edge daemon with the viewer on the edge's own session.
rerun-sdk is an optional extra (``pip install 'zoffload[view]'``), imported only here, lazily.
"""

from __future__ import annotations

from types import ModuleType

from zoffload.runtime.errors import ConfigError

INSTALL_HINT = "the live view needs rerun-sdk: pip install 'zoffload[view]' (rerun-sdk 0.41)"


class ViewError(ConfigError):
    """The viewer cannot start: rerun-sdk missing, a port in use, a file not writable (the
    command line reports it as a configuration error)."""


def rerun() -> ModuleType:
    """The ``rerun`` module, or a ``ViewError`` with the install hint."""
    try:
        import rerun as rr
    except ImportError as exc:
        raise ViewError(f"{INSTALL_HINT} ({exc})") from exc
    return rr
