"""The actor process: batched env stepping, policy inference, publishing transitions (the runtime issue)."""
