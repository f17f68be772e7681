"""facelab.experiment: protocol schema, trial design, participant sessions and the CLI.

Importing this package is cheap: psychopy is imported only by the runner modules.
"""

__all__ = ["design", "errors", "protocol"]
