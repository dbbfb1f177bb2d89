"""The runtime: the job service and its store, the processes of a job on this machine (spawn, respawn, scale),
host agents, in-process training and background evaluations. The ``convoy`` command line that drives it is
``convoy.cli``."""
