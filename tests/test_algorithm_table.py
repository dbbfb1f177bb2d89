"""The algorithm table (``convoy.config.ALGORITHMS``) is the one place an algorithm is declared: its rows agree with
the classes they name."""

from __future__ import annotations

import pytest

from convoy.algos.algorithm import NetworkAgent
from convoy.algos.listening import HearsMessages
from convoy.algos.memory import MemoryModule
from convoy.algos.registry import algorithm_class
from convoy.config import ALGORITHMS, job_config


@pytest.mark.parametrize("name", list(ALGORITHMS))
def test_each_row_names_its_class_and_says_what_it_hears(name: str) -> None:
    row, cls = ALGORITHMS[name], algorithm_class(name)
    assert issubclass(cls, NetworkAgent) and cls.name == name
    assert row.listens == issubclass(cls, HearsMessages)
    assert row.needs_messages == (cls.uses_messages and not issubclass(cls, MemoryModule))
    assert row.summary and set(row.config.model_fields) >= {"lr", "gamma", "hidden"}
    # a reader follows at most two levels of inheritance to the shared base (mixins aside)
    assert len([c for c in cls.__mro__ if issubclass(c, NetworkAgent)]) <= 3, cls.__mro__


def test_evaluation_probes_follow_the_table() -> None:
    from convoy.validation import ConfigError

    for name, row in ALGORITHMS.items():
        params = {"teacher": "t.pt"} if name == "codbc" else {}
        for messages, allowed in (("noise", row.listens), ("predicted", not row.needs_messages)):
            if allowed:
                job_config(algo=name, algo_params=params, eval_messages=messages)
            else:
                with pytest.raises(ConfigError) as info:
                    job_config(algo=name, algo_params=params, eval_messages=messages)
                assert info.value.field == "eval_messages"
