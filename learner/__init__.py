"""Training: the one trainer core (``core``), the in-process trainer (``inprocess``) and the distributed learner
process (``service``) that feed it, what every run reports (``runlog``, ``metrics``) and process tuning
(``runtime``)."""
