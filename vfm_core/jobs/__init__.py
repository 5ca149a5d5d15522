"""The jobs behind the command line: the prequential study, tuning, drift and diagnosis."""
