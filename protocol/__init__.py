"""What every Convoy process agrees on: job and algorithm configs, Zenoh key expressions, the wire schema.

Filled in by the distributed-runtime issue; the environment configs it will embed live in ``envs``.
"""
