"""tools wing: the ``viotb`` command line, benchmarks, the regression suite, plots and reports."""
