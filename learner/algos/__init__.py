"""One module per algorithm; ``learner.registry`` maps names to classes."""
