"""Where the live view's socket is (the publisher a run sends to it with: assembly/live.py).

By default (``default_live_path``) (``default_live_path``): ``$BEAMCTL_LIVE_SOCKET``, else
``live.sock`` beside the service's control socket (service/control.py: /run/beamctl for the lab's
service, else $XDG_RUNTIME_DIR/beamctl or /tmp/beamctl-<uid>), so that ``beamctl monitor`` and
``beamctl run --live`` find each other with their defaults.
"""

from __future__ import annotations

import argparse
import os

from beamctl.service.control import default_socket_path

SOCKET_ENV = "BEAMCTL_LIVE_SOCKET"


def default_live_path() -> str:
    """``$BEAMCTL_LIVE_SOCKET``, else ``live.sock`` beside the default control socket."""
    return os.environ.get(SOCKET_ENV) or str(default_socket_path().with_name("live.sock"))


def add_live_argument(p: argparse.ArgumentParser) -> None:
    """``--live [ADDRESS]`` of a command that runs the loop: the socket of ``beamctl monitor``
    (without ADDRESS: where the monitor listens by default)."""
    p.add_argument("--live", nargs="?", const=default_live_path(), metavar="ADDRESS",
                   help="send live values to `beamctl monitor` listening at ADDRESS (a UNIX socket; "
                        f"default {default_live_path()}); with nobody listening the values are dropped")
