"""facelab.analysis: session logs -> one tidy table -> statistics, figures and reports."""
