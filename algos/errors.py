"""Errors the CLI and the API report to users, importable without torch (``convoy --help`` stays fast)."""

from __future__ import annotations


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message names the path and the fix."""
