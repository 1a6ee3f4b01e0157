"""Optional dependencies: imported when a command needs them, refused in one line naming the
extra that installs them when they are missing."""

from __future__ import annotations

import importlib
from types import ModuleType


class MissingExtraError(ImportError):
    """A package of an optional extra is not installed."""


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module``; if it is missing, raise ``MissingExtraError`` saying which extra of
    beamctl installs it (``purpose``: what it is needed for)."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingExtraError(f"{purpose} needs {module.split('.')[0]}, which is not installed: "
                                f"pip install 'beamctl[{extra}]'") from None
