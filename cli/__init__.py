"""The ``convoy`` command line: one module per command, every flag drawn from the config models; what the
commands run lives in ``convoy.services`` (the runtime) and the libraries below it."""
