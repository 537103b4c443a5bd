"""One root exception, split by whose fault it is (after h11's Local/RemoteProtocolError).

Bad input from the network is never raised out of the loop: it is counted, logged and
reported. Bad configuration raises ConfigError before anything starts.
"""

from __future__ import annotations


class RoverBridgeError(Exception):
    """Root of every error rover-bridge raises on purpose."""


class ConfigError(RoverBridgeError):
    """The user's configuration (profile, command line) is wrong. Carries every problem found."""

    def __init__(self, problems: list[str]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class LinkError(RoverBridgeError):
    """A MAVLink link could not be opened (nothing listening, no device, address in use): one line that
    says which link and what to check. Not a configuration error: the same command may work once the
    autopilot is up, so the process exits 1 (systemd restarts it), not 2."""


class RemoteError(RoverBridgeError):
    """A peer sent something we cannot use (malformed, out of range, refused)."""


class LocalError(RoverBridgeError):
    """We were asked to do something impossible (a programming or state error on our side)."""
