# syntax=docker/dockerfile:1
# The Convoy image: the `convoy` CLI (host agents, learner, actors) on CPU torch. Built by compose.yaml
# (`docker compose build`), or alone from the repository root:
#   docker build -f docker/convoy.Dockerfile -t convoy:local .
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

# CPU torch from PyTorch's own index first: `pip install .` then finds `torch>=2.3` satisfied and does not pull
# the CUDA wheels (gigabytes) from PyPI.
RUN pip install torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu

WORKDIR /opt/convoy
# Only what the package needs (the folders of pyproject's [tool.setuptools.package-dir] — tests/test_compose.py
# checks the two lists agree), so a local .venv/ or runs/ never enters the image.
COPY pyproject.toml README.md ./
COPY convoy/ convoy/
COPY protocol/ protocol/
COPY envs/ envs/
COPY algos/ algos/
COPY actors/ actors/
COPY analysis/ analysis/
COPY learner/ learner/
COPY api/ api/
COPY services/ services/
COPY cli/ cli/
RUN pip install . && convoy --help > /dev/null

# Not root. /runs is where compose mounts the learner's volume; a fresh named volume takes this owner.
RUN useradd --create-home --uid 1000 convoy && mkdir /runs && chown convoy:convoy /runs
USER convoy
WORKDIR /home/convoy

CMD ["convoy", "--help"]
