"""The command line, ``ari-sfm``: the group and the calibration, reconstruction, simulation and OpenPTV
commands (:mod:`.commands`), the particle commands (:mod:`.particles`) and the COLMAP ones (:mod:`.colmap`),
their option checks before any work (:mod:`.checks`), the config file (:mod:`.config`) and how a command
runs in its process: log levels, SIGINT/SIGTERM, errors as one line, the exit (:mod:`.process`)."""
from .commands import main
from .process import user_errors

__all__ = ["main", "user_errors"]
