"""Adam without ``torch.optim``'s machinery: one fused kernel call per parameter group, nothing imported lazily.

``torch.optim.Adam`` wraps its methods in ``torch._disable_dynamo``, whose first call imports
``torch._dynamo`` (about 1.5 s on a 2-core CPU, and more memory): every ``nimbus-train`` process and
every benchmark worker paid it before its first iteration.  Training needs none of that: the update
itself is one call to torch's fused Adam kernel (``torch._fused_adam_``, what
``torch.optim.Adam(fused=True)`` runs), on the CPU, CUDA and MPS alike.

:class:`Adam` keeps the parts of the optimizer interface this project uses: ``param_groups`` (each
with ``lr``, ``betas``, ``eps``, ``weight_decay`` and any extra keys such as ``name``), ``state`` (per
parameter ``step``, ``exp_avg``, ``exp_avg_sq``: densification surgery edits them), ``step``,
``zero_grad`` and a ``state_dict`` in ``torch.optim``'s own layout, so that checkpoints written
before it load unchanged.  Its update is the one ``torch.optim.Adam(fused=True)`` makes, bit for bit
(``tests/test_adam.py``).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any, Iterable

import torch
from torch import Tensor

#: Hyperparameters every group gets unless it sets its own.
DEFAULTS = {"lr": 1e-3, "betas": (0.9, 0.999), "eps": 1e-8, "weight_decay": 0.0}


class Adam:
    """Adam (Kingma & Ba) over parameter groups, updated by torch's fused kernel.

    Parameters
    ----------
    groups
        Dicts with ``params`` (a list of leaf tensors) and optionally ``lr``, ``betas``, ``eps``,
        ``weight_decay`` and keys of the caller's own (kept as they are), or an iterable of tensors.
    lr, betas, eps, weight_decay
        Defaults for the groups that do not set their own.
    """

    def __init__(self, groups: Iterable[dict] | Iterable[Tensor], lr: float = DEFAULTS["lr"],
                 betas: tuple[float, float] = DEFAULTS["betas"], eps: float = DEFAULTS["eps"],
                 weight_decay: float = DEFAULTS["weight_decay"]) -> None:
        self.defaults = {"lr": lr, "betas": tuple(betas), "eps": eps, "weight_decay": weight_decay, "fused": True}
        groups = list(groups)
        if groups and isinstance(groups[0], Tensor):
            groups = [{"params": groups}]
        self.param_groups: list[dict[str, Any]] = []
        seen: set[int] = set()
        for group in groups:
            params = list(group["params"])
            for p in params:
                if not p.is_leaf or not p.requires_grad:
                    raise ValueError("Adam optimises leaf tensors with requires_grad=True")
                if id(p) in seen:
                    raise ValueError("a tensor appears in more than one Adam parameter group")
                seen.add(id(p))
            self.param_groups.append({**self.defaults, **group, "params": params})
        #: Per parameter: ``step`` (a float32 scalar tensor on its device), ``exp_avg``, ``exp_avg_sq``.
        self.state: dict[Tensor, dict[str, Tensor]] = defaultdict(dict)

    @torch.no_grad()
    def step(self) -> None:
        """One Adam update of every parameter that has a gradient (the others are left alone)."""
        for group in self.param_groups:
            by_device: dict[tuple, list[list[Tensor]]] = {}
            for p in group["params"]:
                if p.grad is None:
                    continue
                if p.grad.is_sparse:
                    raise RuntimeError("Adam does not take sparse gradients")
                state = self.state[p]
                if not state:
                    state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                    state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                lists = by_device.setdefault((p.device, p.dtype), [[], [], [], [], []])
                for lst, t in zip(lists, (p, p.grad, state["exp_avg"], state["exp_avg_sq"], state["step"])):
                    lst.append(t)
            beta1, beta2 = group["betas"]
            for params, grads, exp_avgs, exp_avg_sqs, steps in by_device.values():
                torch._foreach_add_(steps, 1)
                torch._fused_adam_(params, grads, exp_avgs, exp_avg_sqs, [], steps, lr=float(group["lr"]),
                                   beta1=beta1, beta2=beta2, weight_decay=group["weight_decay"], eps=group["eps"],
                                   amsgrad=False, maximize=False, grad_scale=None, found_inf=None)

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_()
                    p.grad.zero_()

    def state_dict(self) -> dict:
        """``torch.optim``'s layout: ``state`` keyed by the parameters' running index, ``param_groups``."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = []
            for p in group["params"]:
                index.setdefault(id(p), len(index))
                ids.append(index[id(p)])
            groups.append({**{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {index[id(p)]: dict(s) for p, s in self.state.items() if s and id(p) in index}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict) -> None:
        """Load a :meth:`state_dict` (or ``torch.optim.Adam``'s): the groups must hold as many tensors as now."""
        saved = state_dict["param_groups"]
        if len(saved) != len(self.param_groups) or any(
                len(s["params"]) != len(g["params"]) for s, g in zip(saved, self.param_groups)):
            raise ValueError("the saved optimizer state has other parameter groups than this optimizer")
        by_index = {}
        for s, g in zip(saved, self.param_groups):
            by_index.update(zip(s["params"], g["params"]))
        self.state = defaultdict(dict)
        for i, s in state_dict["state"].items():
            p = by_index.get(int(i))
            if p is None:
                continue
            loaded = {}
            for key, value in s.items():
                if key == "step":
                    loaded[key] = torch.as_tensor(value, dtype=torch.float32).to(p.device).reshape(())
                elif isinstance(value, Tensor):
                    loaded[key] = value.to(device=p.device, dtype=p.dtype)
                else:
                    loaded[key] = value
            self.state[p] = loaded
        self.param_groups = [{**{k: v for k, v in s.items() if k != "params"}, "params": g["params"]}
                             for s, g in zip(saved, self.param_groups)]
        for g in self.param_groups:
            g["betas"] = tuple(g["betas"])
