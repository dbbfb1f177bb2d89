"""FLOPs of a call as torch counts them (``FlopCounterMode``), including the fused recurrent layers it misses.

Why: torch's formula table knows ``mm``/``addmm``/``bmm``/convolutions, but a CPU ``nn.LSTM`` runs as one oneDNN
kernel per layer (``aten.mkldnn_rnn_layer`` and its backward) and a CUDA one as cuDNN's (``aten._cudnn_rnn``), which
it counts as zero. The memory modules of MA-MeSN-MM and MA-BoN-MM are such LSTMs, so without these formulas their
updates' FLOPs — and their fraction of the matmul peak — were undercounted by the whole recurrent layer.

The formulas count exactly what the same layer costs when torch runs it step by step (``mkldnn`` disabled), as
``tests/test_algo_benchmarks.py`` checks: forward, 2·rows·(|W_ih| + |W_hh|) per layer and direction, where rows =
steps × batch; backward twice that (the gradients of the inputs and of the weights, torch's convention for ``mm``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch
from torch.utils._pytree import tree_map

aten = torch.ops.aten


def _rnn_forward(rows_shape: Sequence[int], weights: Sequence[Sequence[int]]) -> int:
    """2 · rows · Σ|W| over the layer's matrices (input, recurrent, and projection if any); biases excluded."""
    rows = math.prod(rows_shape[:-1])
    return 2 * rows * sum(math.prod(w) for w in weights if len(w) == 2)


def mkldnn_rnn_flops(input: Any, w_ih: Any, w_hh: Any, *args: Any, **kwargs: Any) -> int:
    return _rnn_forward(input, [w_ih, w_hh])


def mkldnn_rnn_backward_flops(input: Any, w_ih: Any, w_hh: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * _rnn_forward(input, [w_ih, w_hh])


def cudnn_rnn_flops(input: Any, weights: Any, *args: Any, **kwargs: Any) -> int:
    return _rnn_forward(input, weights)


def cudnn_rnn_backward_flops(input: Any, weights: Any, *args: Any, **kwargs: Any) -> int:
    return 2 * _rnn_forward(input, weights)


RNN_FLOPS: dict[Any, Callable[..., int]] = {
    aten.mkldnn_rnn_layer: mkldnn_rnn_flops,
    aten.mkldnn_rnn_layer_backward: mkldnn_rnn_backward_flops,
    aten._cudnn_rnn: cudnn_rnn_flops,
    aten._cudnn_rnn_backward: cudnn_rnn_backward_flops,
}


def op_flops(func: Any, args: Sequence[Any]) -> int | None:
    """The FLOPs of one fused recurrent-layer call (``func`` an aten overload), or None for any other op."""
    formula = RNN_FLOPS.get(func.overloadpacket)
    if formula is None:
        return None
    shapes = tree_map(lambda a: a.shape if isinstance(a, torch.Tensor) else a, list(args))
    return formula(*shapes)


def count_flops(fn: Callable[[], Any]) -> tuple[int, dict[str, int]]:
    """FLOPs torch itself counts for ``fn()`` (matmuls, convolutions, fused RNN layers; forward and backward), total
    and by op."""
    from torch.utils.flop_counter import FlopCounterMode

    mode = FlopCounterMode(display=False, custom_mapping=RNN_FLOPS)
    with mode:
        fn()
    by_op = {str(op): int(v) for op, v in mode.get_flop_counts().get("Global", {}).items()}
    return int(mode.get_total_flops()), by_op
