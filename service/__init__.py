"""The lab service: its configuration and assembly (``setup``), the control socket
(``control``), the live values it publishes (``live``) and the browser view of them
(``monitor``), systemd's readiness notification (``sdnotify``)."""

import beamctl.common  # noqa: F401  (single-threaded BLAS, before numpy is imported)
