"""What the edge server asks of each of its services (mapping, detection).

A service declares its subscribers, queryables and publishers on the edge's one Zenoh session in
``start``, reports a few numbers for the edge's 1 Hz status message in ``status``, drops the state
of a robot gone idle in ``evict``, and in ``stop``
stops listening, finishes or abandons its queued work, joins its threads and writes whatever it
keeps (the mapping service exports its maps). The server starts services in order and stops them in
reverse; the session itself belongs to the server, which closes it after the last service stopped.
"""

from __future__ import annotations

from typing import Protocol

import zenoh


class EdgeService(Protocol):
    @property
    def name(self) -> str:
        """Short name for logs ("mapping", "detector")."""
        ...

    def start(self, session: zenoh.Session) -> None:
        """Warm up, then declare everything the service serves on ``session``."""
        ...

    def status(self) -> dict[str, float]:
        """Values merged into the edge's status message; called from the status thread."""
        ...

    def evict(self, robot: str) -> None:
        """Forget a robot the admission expired (answer what it has waiting, drop its state, the
        mapping service exports its map first). Called from the status thread."""
        ...

    def stop(self) -> None:
        """Stop listening, join the service's threads, write what it keeps. Called once."""
        ...
