"""Measuring policies: flights, tables, statistics, the validation choice, grounding, figures and plots."""

ENSEMBLE_SEP = "+"  # joins an ensemble's weights files in the weights column of results.csv
