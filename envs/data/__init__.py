"""data wing: EuRoC ASL and TUM files, recording a scenario to disk, and evaluating an estimator on a dataset."""
