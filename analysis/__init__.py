"""Judging trained agents: greedy evaluation under any message source or channel, recording a policy's
messages and actions, and the communication metrics of the paper's Table 1."""
