"""OpenPTV in and out: import an OpenPTV experiment as a dataset, export a calibration as
OpenPTV orientation files. Conventions (taken from liboptv's sources) in :mod:`.conventions`."""
from .exporter import ExportSummary, export_openptv
from .importer import import_experiment, read_experiment

__all__ = ["ExportSummary", "export_openptv", "import_experiment", "read_experiment"]
