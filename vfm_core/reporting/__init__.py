"""HTML reports of the study, the drift test and the diagnosis."""
