"""Error against run time: what ``torch-ao bench`` measures and reports, without any command-line code.

* :mod:`.sweep`: :func:`run_bench` times each method at each preset on reference views (from
  :mod:`torch_ao.views`) and measures its error; sweep sizes :data:`QUICK` and :data:`DEFAULT`.
* :mod:`.recommend`: the Pareto front, the mean over scenes and :func:`recommend` (per scene, the
  cheapest configuration whose MAE is within a tolerance of the best).
* :mod:`.files`: the report's ``bench.csv``, ``bench.md``, ``report.json`` and plots.
* :mod:`.auto`: :func:`auto_choice`, the recommendation for one G-buffer file (``torch-ao ao --auto``).
* :mod:`.background`: background costs nothing (full, half and all-background frames).
"""
from .auto import AUTO_PRESETS, auto_choice
from .background import background_frames, background_scaling
from .files import REPORT_VERSION, load_report, markdown_report, plot_error_vs_time, write_csv, write_report
from .recommend import DEFAULT_TOLERANCE, aggregate_rows, pareto_front, recommend
from .sweep import (COLUMNS, DEFAULT, QUICK, SIZE_OPTIONS, BenchSettings, MethodFactory, accepted_arguments, available_methods,
                    environment, make_method, run_bench, time_call, time_calls)

__all__ = ["AUTO_PRESETS", "auto_choice", "background_frames", "background_scaling", "REPORT_VERSION", "load_report",
           "markdown_report", "plot_error_vs_time", "write_csv", "write_report", "DEFAULT_TOLERANCE",
           "aggregate_rows", "pareto_front", "recommend", "COLUMNS", "DEFAULT", "QUICK", "SIZE_OPTIONS", "BenchSettings",
           "MethodFactory", "accepted_arguments", "available_methods", "environment", "make_method", "run_bench",
           "time_call", "time_calls"]
