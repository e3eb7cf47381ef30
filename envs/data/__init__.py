"""data wing: EuRoC ASL and TUM files, recording a scenario, and evaluating an estimator on a dataset."""
