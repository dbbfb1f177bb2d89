"""MA-MeSN-MM (section 4.1): MA-MeSN with an LSTM memory module per agent, for execution without a channel.

Training is MA-MeSN's, unchanged, plus the memory module's supervised loss on the same batches (``algos/memory.py``):
each agent's module learns to predict the N − 1 messages it hears from its own observation history. At execution
the policy network f″ reads the true messages (``sent``), the predictions (``predicted``: fully decentralised) or
the true messages with the lost ones replaced by predictions (a lossy channel) — chosen per evaluation.
"""

from __future__ import annotations

from convoy.algos.ma_mesn import MAMeSN
from convoy.algos.memory import MemoryModule
from convoy.config import MeSNMMConfig


class MAMeSNMM(MemoryModule, MAMeSN):
    """MA-MeSN whose agents also learn to predict their peers' messages."""

    name = "ma-mesn-mm"
    cfg: MeSNMMConfig
