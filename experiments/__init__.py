"""The paper's tables and the other experiments, run as modules from the repository root:
`python -m experiments.table1_foreground --quick` (experiments/README.md)."""
