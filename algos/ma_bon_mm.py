"""MA-BoN-MM (section 4.2): MA-BoN with an LSTM memory module per agent predicting the broadcast message.

Training is MA-BoN's plus the memory module's supervised loss (``algos/memory.py``); at execution g′ reads the true
broadcast, the agent's own prediction of it (no channel), or the broadcast with lost copies replaced by predictions.
"""

from __future__ import annotations

from convoy.algos.ma_bon import MABoN
from convoy.algos.memory import MemoryModule
from convoy.config import BoNMMConfig


class MABoNMM(MemoryModule, MABoN):
    """MA-BoN whose agents also learn to predict the broadcast message."""

    name = "ma-bon-mm"
    cfg: BoNMMConfig
