"""What runs: the ``convoy`` CLI and, later, the host agent and supervisor (the composition root)."""
