"""Compiled inference: run the processor (the message passing, ~75 % of a step) through ``torch.compile``.

Inductor fuses the processor's element-wise work (bias adds, ReLUs, LayerNorms, residual adds) into C++ loops
around the matrix products, which the eager CPU path runs as separate passes over the (E, L) edge latents.
Measured on the full checkpoint, tshirt_jacket at 3.5 cm (1,637 vertices), one thread: 12-15 % less time per
step (docs/BENCHMARKS.md, session 6). The price is a one-off compilation of about 10-80 s on the first step
(shapes are marked dynamic, so later frames, clips and outfits with other edge counts reuse it; Inductor also
caches on disk), which is why it is opt-in (``--compile``).

Inference by default (gradients off inside); training (``smln train --compile``) wraps the processor with
``training=True``, so AOTAutograd compiles the backward pass as well (measured: 13-18 % less time per training
step, tshirt_jacket on a walk, one thread, after a one-off compilation of about 2 minutes;
``bench/train_step_speed.py``). If the compiler is unavailable (no C++ toolchain) or compilation fails, the
processor falls back to eager with one warning; the results are the same up to float rounding.
"""

from __future__ import annotations

import contextlib
import copy
import warnings

import torch
from torch import nn


class CompiledProcessor(nn.Module):
    """Wraps a processor: calls ``torch.compile(processor, dynamic=True)``, eager on any compilation failure.

    Args:
        processor: the processor (float32 or a :class:`~smln.model.precision.LowPrecisionProcessor`); shared,
            not copied.
        training: False (inference): the compiled call runs under ``torch.no_grad``; True: gradients flow through
            it (the compiled graph includes the backward pass).
    """

    def __init__(self, processor: nn.Module, training: bool = False) -> None:
        super().__init__()
        self.inner = processor
        self.for_training = training
        # not a registered submodule: the wrapper's state_dict is the processor's, under ``inner.``
        object.__setattr__(self, "_compiled", torch.compile(processor, dynamic=True))
        self.failed: str | None = None

    def forward(self, *args, **kwargs) -> torch.Tensor:
        """Same contract as the wrapped processor's forward."""
        if self.failed is None:
            try:
                with contextlib.nullcontext() if self.for_training else torch.no_grad():
                    return self._compiled(*args, **kwargs)
            except Exception as exc:  # noqa: BLE001 - any compiler failure: fall back, never break a rollout
                self.failed = f"{type(exc).__name__}: {exc}".splitlines()[0][:300]
                warnings.warn(f"torch.compile of the processor failed ({self.failed}); running it eager",
                              RuntimeWarning, stacklevel=2)
        return self.inner(*args, **kwargs)


def with_compiled_processor(model: nn.Module, training: bool = False) -> nn.Module:
    """A shallow copy of the SMLN whose processor is compiled (all modules, the weights included, shared with
    ``model``, which is left as it was). ``training``: gradients flow through the compiled processor and the copy
    is in training mode (:class:`CompiledProcessor`)."""
    fast = copy.copy(model)
    fast._modules = dict(model._modules)  # a new module table: replacing the processor leaves ``model`` intact
    # a new wrapper per call is cheap: Dynamo keys its compiled code on the processor's code and guards, so a
    # second wrapper (or a new bfloat16 copy of the processor) reuses the first compilation (measured: the
    # second rollout's first step 13 ms instead of 8.6 s)
    fast._modules["processor"] = CompiledProcessor(model.processor, training=training)
    fast.training = training
    return fast
