"""MA-BoN-MM (section 4.2): MA-BoN with an LSTM memory module per agent predicting the broadcast message.

Training is MA-BoN's plus the memory module's supervised loss (``algos/memory.py``); at execution g′ reads the true
broadcast, the agent's own prediction of it (no channel), or the broadcast with lost copies replaced by predictions.
"""

from __future__ import annotations

from typing import ClassVar

from convoy.algos.ma_bon import MABoN
from convoy.algos.memory import MemoryModule
from convoy.config import AlgoConfig, BoNMMConfig


class MABoNMM(MemoryModule, MABoN):
    """MA-BoN whose agents also learn to predict the broadcast message."""

    name = "ma-bon-mm"
    population = True
    config_model: ClassVar[type[AlgoConfig]] = BoNMMConfig
    cfg: BoNMMConfig
