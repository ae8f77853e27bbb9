"""Counting host synchronisations per training step of a real `aesplat fit`, on the CPU.

On a GPU, a host synchronisation makes the CPU wait until the device has finished everything queued before it:
``.item()``, ``bool(tensor)``, ``float(tensor)``, ``.cpu()``, ``.tolist()``, ``.numpy()``, and the operations
whose output shape depends on the data (``nonzero``, boolean-mask indexing, ``masked_select``, ``unique``,
``repeat_interleave`` without an output size, ``torch.equal``). On the CPU nothing waits, but every such call
still happens, so it can be counted: ``HostSyncCounter`` is a Lightning profiler (pass it as
``--trainer.profiler tests.train.host_syncs.HostSyncCounter``) that, while a fit runs, intercepts every aten
operation in the main thread and the Python-level transfers, and records each one that would synchronise a GPU,
step by step.

What counts as "on the device": every tensor except those the step itself made on the host. Host tensors are
the results of a counted transfer (``.cpu()`` and friends) and of factories (``torch.tensor(1.0)``,
``torch.zeros(3)``: operations without tensor inputs), and whatever is computed from host tensors only. So a
value fetched once with ``.cpu()`` and then logged (Lightning converts it with ``.item()`` on every step) costs
one synchronisation, as it would on a GPU. A step's window runs from the batch's move to the device to the
fetch of the next batch; the data loader's own work (host-side, in its workers on a GPU run) is left out.
"""

from __future__ import annotations

import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import torch
from lightning.pytorch.profilers import Profiler
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torch.utils.weak import WeakTensorKeyDictionary

aten = torch.ops.aten
# Operations that read a device value on the host (or need it to size their output).
_SYNCING = {
    aten._local_scalar_dense.default: "item",  # .item(), bool(t), float(t), int(t), `if t:`
    aten.nonzero.default: "nonzero",
    aten.masked_select.default: "masked_select",
    aten.equal.default: "equal",
}
_SYNCING_PACKETS = {
    aten._unique: "unique",
    aten._unique2: "unique",
    aten.unique_dim: "unique",
    aten.unique_consecutive: "unique",
}
_PROJECT = str(Path(__file__).resolve().parents[2])


class _Mode(TorchDispatchMode):
    def __init__(self, counter: HostSyncCounter) -> None:
        super().__init__()
        self.counter = counter

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        counter = self.counter
        if not counter.counting:
            return out
        inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        on_device = [t for t in inputs if not counter.is_host(t)]
        name = _SYNCING.get(func) or _SYNCING_PACKETS.get(func.overloadpacket)
        if name is None and func.overloadpacket in (aten.index, aten.index_put, aten.index_put_):
            indices = args[1] if len(args) > 1 else kwargs.get("indices", ())
            if any(i is not None and i.dtype in (torch.bool, torch.uint8) for i in indices):
                name = "boolean-mask indexing"
        if name is None and func is aten.repeat_interleave.Tensor and kwargs.get("output_size") is None:
            name = "repeat_interleave"
        if name is not None and on_device:
            counter.record(name)
        outputs = [t for t in tree_flatten(out)[0] if isinstance(t, torch.Tensor)]
        made_here = func.overloadpacket in (aten.lift_fresh, aten.lift_fresh_copy)  # torch.tensor(data)
        for t in outputs:
            if on_device and not made_here:
                counter.host.pop(t, None)
            else:
                counter.host[t] = True
        return out


class HostSyncCounter(Profiler):
    """Per training step, the host synchronisations a GPU run of the same code would make (see the module).

    ``steps[i]`` lists step i's synchronisations as ``"what at file:line"`` (the innermost frame in this
    repository, else the innermost one). The newest instance is ``HostSyncCounter.last``.
    """

    last: HostSyncCounter | None = None

    def __init__(self) -> None:
        super().__init__()
        self.steps: list[list[str]] = []
        self.counting = False
        self.host = WeakTensorKeyDictionary()
        self._mode: _Mode | None = None
        self._patched: dict[str, object] = {}
        HostSyncCounter.last = self

    # ------------------------------------------------------------------------------------- the step window
    def start(self, action_name: str) -> None:
        if action_name.endswith(("train_dataloader_next", ".on_train_epoch_end", ".on_train_end")):
            self.counting = False
        elif action_name.endswith(".batch_to_device") and self._mode is not None:
            self.steps.append([])
            self.counting = True

    def stop(self, action_name: str) -> None:
        pass

    def summary(self) -> str:
        return "host synchronisations per step: " + ", ".join(str(len(s)) for s in self.steps)

    def setup(self, stage: str, local_rank: int | None = None, log_dir: str | None = None) -> None:
        super().setup(stage, local_rank, log_dir)
        if stage == "fit" and self._mode is None:
            self._begin()

    def teardown(self, stage: str | None) -> None:
        self._end()
        super().teardown(stage)

    @contextmanager
    def count(self) -> Iterator[list[str]]:
        """Count the host synchronisations of a block of code (outside a fit): yields the list it fills."""
        self._begin()
        self.steps.append([])
        self.counting = True
        try:
            yield self.steps[-1]
        finally:
            self._end()

    def _begin(self) -> None:
        self._patch()
        self._mode = _Mode(self)
        self._mode.__enter__()

    def _end(self) -> None:
        if self._mode is not None:
            self.counting = False
            self._mode.__exit__(None, None, None)
            self._mode = None
            self._unpatch()

    # ------------------------------------------------------------------------------------- bookkeeping
    def is_host(self, t: torch.Tensor) -> bool:
        return t in self.host

    def record(self, what: str) -> None:
        frames = traceback.extract_stack()[:-2]
        ours = [  # the repository's own frames (a virtual environment inside the checkout is not ours)
            f
            for f in frames
            if f.filename.startswith(_PROJECT)
            and "site-packages" not in Path(f.filename).parts
            and Path(f.filename).name != "host_syncs.py"
        ]
        frame = (ours or frames)[-1]
        where = f"{Path(frame.filename).parent.name}/{Path(frame.filename).name}:{frame.lineno}"
        below = frames[frames.index(frame) + 1 :]
        if below and "site-packages" in (parts := Path(below[0].filename).parts):
            where += f" (in {parts[parts.index('site-packages') + 1]})"
        self.steps[-1].append(f"{what} at {where}")

    def _patch(self) -> None:
        """Python-level transfers (they bypass the dispatcher on a CPU tensor): count, and mark the result."""
        counter = self

        def transfer(name, original):
            def wrapper(self, *args, **kwargs):
                if not counter.counting or counter.is_host(self):
                    return original(self, *args, **kwargs)
                counter.record(f".{name}()")
                with torch.utils._python_dispatch._disable_current_modes():
                    result = original(self.detach().clone() if name == "cpu" else self, *args, **kwargs)
                if isinstance(result, torch.Tensor):
                    counter.host[result] = True
                return result

            return wrapper

        for name in ("cpu", "tolist", "numpy"):
            original = getattr(torch.Tensor, name)
            self._patched[name] = original
            setattr(torch.Tensor, name, transfer(name, original))

    def _unpatch(self) -> None:
        for name, original in self._patched.items():
            setattr(torch.Tensor, name, original)
        self._patched.clear()
