"""Convoy: train cooperating, communicating agents.

The repository keeps its folders by role at the top (``envs/``, ``learner/``, ``actors/``, ``api/``,
``services/``, ``protocol/``); installed, they import as ``convoy.envs``, ``convoy.learner``, … (see
``[tool.setuptools.package-dir]`` in ``pyproject.toml``), so nothing generic lands at the top of site-packages.
"""

__version__ = "0.1.0"
