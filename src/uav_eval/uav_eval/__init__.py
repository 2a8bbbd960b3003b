"""Measuring policies: flights, tables, statistics, the validation choice, grounding, figures and plots."""
