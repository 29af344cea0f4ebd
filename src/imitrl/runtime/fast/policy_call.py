"""A policy's per-step call on a dict of tensors, and networks called without hook checks.

Accelerated internals of :mod:`imitrl.runtime.paths` (import them from there, nowhere else).

**Per-step calls.** A rollout calls its policy once per env step. Through tensordict's
modules that call costs several times the network's forward at small batches (issue 16:
``ProbabilisticActor`` 3.1 s over 5,494 CartPole calls, the numpy expert 0.3 s): the
``dispatch`` and skip-existing wrappers, the interaction-type context, a distribution
built to take an argmax, a ``get``/``set`` per key. :class:`TensorPolicy` does what
``policy(td)`` does to ``td``'s entries, on a plain ``dict`` ``key -> tensor``, for the
modules imitrl builds:

=================================== ================================================
module                              replayed as
=================================== ================================================
``TensorDictSequential``            its modules in order
``Module``, ``TensorDictModule``    ``module.module(*in_keys) -> out_keys``
``ProbabilisticActor``              the network, then the distribution's
                                    ``deterministic_sample`` (``mode`` under MODE;
                                    one ``rsample``/``sample`` under RANDOM, as
                                    tensordict draws it, from the same RNG)
:class:`~imitrl.policies.Expert`    its function of ``in_keys``, cast by ``cast_label``
``Expert.as_actor``'s executor      ``ACTION <- EXPERT_ACTION``
:class:`~imitrl.policies.BetaMixer` ``BetaMixer.mix`` (the same coins)
=================================== ================================================

The networks inside run by :func:`direct_call`: an ``nn.Sequential`` (or
:class:`~imitrl.policies.heads.Chain`) of hookless modules calls each child's
``forward`` without ``nn.Module.__call__``'s hook bookkeeping (about a fifth of a small
MLP's call at batch 1). Any other module (an actor under MEAN or MEDIAN, one that
writes its log-probability), or a module with hooks runs through its own ``forward`` on
a TensorDict of the dict's entries. Each replay runs the module's own code on the same tensors, so the outputs are the module's to the bit
(``tests/runtime/test_paths.py``, the seam's test, checks it for every learner head and the DAgger behaviour
policy).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import cast

import torch
from tensordict import TensorDict
from tensordict.nn import (
    ProbabilisticTensorDictModule,
    TensorDictModule,
    TensorDictModuleBase,
    TensorDictSequential,
    skip_existing,
)
from torch import nn
from torch.nn import functional as F
from torch.nn.utils import parametrize
from torchrl.envs.utils import ExplorationType, exploration_type
from torchrl.modules import ProbabilisticActor

from imitrl import keys
from imitrl.compat import global_module_hooks, hooked, plain_call
from imitrl.policies.distributions import GreedyCategorical
from imitrl.policies.experts import Expert, _ExecuteExpert
from imitrl.policies.heads import Chain, Squash
from imitrl.policies.mixture import BetaMixer
from imitrl.policies.modules import Module
from imitrl.policies.normalization import ObservationNormalizer
from imitrl.runtime.fast import categorical, tanh_normal

__all__ = ["TensorPolicy", "Values", "direct_call"]


def direct_call(module: nn.Module) -> Callable[..., torch.Tensor]:
    """``module``'s call with ``nn.Module.__call__`` skipped where it only checks for hooks.

    A module without hooks (none of its own, none global) is called as ``module.forward``;
    an ``nn.Sequential`` of such modules, or a ``Chain`` (its first child may take several
    inputs), as its children's direct calls in order; ``nn.Linear`` as ``F.linear`` with
    its parameters, ``nn.Tanh`` as ``torch.tanh``, a ``Squash`` or an
    ``ObservationNormalizer`` (exactly those classes) as its forward with its buffers read
    once (:func:`_bound_forward`). The same code on the same tensors, so the same
    bits. Anything with a hook is called as ``module`` itself. Decided when called: hooks
    registered afterwards are not seen (build it per rollout, or per fit).
    """
    if not isinstance(module, nn.Module) or global_module_hooks() or hooked(module):
        return module
    forward = type(module).forward
    if forward is nn.Sequential.forward or forward is Chain.forward:
        children = [direct_call(child) for child in cast(nn.Sequential, module)]  # or a Chain
        if not children:
            return module
        first, rest = children[0], children[1:]

        def chain(*inputs: torch.Tensor) -> torch.Tensor:  # Sequential: one input
            x = first(*inputs)
            for child in rest:
                x = child(x)
            return x

        return chain
    if type(module) is nn.Tanh:
        return torch.tanh  # nn.Tanh.forward is torch.tanh(input)
    if type(module) is Squash or type(module) is ObservationNormalizer:  # not a subclass's
        return _bound_forward(module)
    if type(module) is nn.Linear and not parametrize.is_parametrized(module):
        # Linear.forward is F.linear(x, self.weight, self.bias): the same call with the
        # parameters bound (the optimizer updates them in place; a rollout builds its
        # calls afresh, so a parameter replaced between rollouts is seen)
        weight, bias = module.weight, module.bias
        return lambda x: F.linear(x, weight, bias)
    return module.forward


_ONE, _TWO = torch.ones(()), torch.full((), 2.0)  # Squash.forward's constants, the same values


def _bound_forward(
    module: Squash | ObservationNormalizer,
) -> Callable[[torch.Tensor], torch.Tensor]:
    """A ``Squash``'s or an ``ObservationNormalizer``'s forward with its buffers read now:
    the same operations on the same values (a ``Squash``'s span computed once, so one fewer
    per call). A normaliser's statistics are updated in place, so a refit during the
    rollout is still seen; a ``Squash``'s bounds replaced afterwards are not."""
    if isinstance(module, Squash):
        low, span = module.low, module.high - module.low
        return lambda x: low + span * (torch.tanh(x) + _ONE) / _TWO
    loc, scale = module.loc, module.scale
    return lambda x: (x - loc) / scale


Values = dict
"""``key -> tensor``: the entries of a rollout's root tensordict (nested keys as tuples)"""
_Step = Callable[[Values], None]


class TensorPolicy:
    """``policy``'s per-step call on a dict of tensors (see the module docstring).

    Build it inside the rollout's ``set_exploration_type`` (the exploration type is
    read once, here) and call it under ``torch.no_grad()``; ``call(values)`` updates
    ``values`` in place as ``policy(td)`` updates ``td``.

    Args:
        policy: the rollout's policy module.
        batch_size: the env's batch size.

    Attributes:
        opaque: some module ran through its own ``forward`` on a TensorDict (it may read
            or write any entry, not only its ``in_keys``/``out_keys``).
        draws: some replayed module draws random numbers (a mixer with ``0 < beta < 1``).
    """

    def __init__(self, policy: TensorDictModuleBase, batch_size: torch.Size) -> None:
        self.batch_size = torch.Size(batch_size)
        self.exploration = exploration_type()
        self.opaque = False
        self.draws = False
        # tensordict's global skip-existing mode would skip modules whose outputs exist
        self._step = self._forward(policy) if skip_existing() else self._compile(policy)

    def __call__(self, values: Values) -> None:
        self._step(values)

    # ------------------------------------------------------------------ dispatch
    def _compile(self, node: TensorDictModuleBase) -> _Step:
        kind = type(node)
        sequence, module = kind is TensorDictSequential, kind in (Module, TensorDictModule)
        if not plain_call(node, sequence=sequence, module=module):
            # e.g. a hooked (safe, projecting) actor, selected out-keys, keyword in-keys
            return self._forward(node)
        if sequence:
            modules = node.module
            return self._sequence(
                list(modules.values() if isinstance(modules, nn.ModuleDict) else modules)
            )
        if module:
            return self._module(node)
        if kind is ProbabilisticActor and self._replayable_actor(node):
            return self._actor(node)
        if isinstance(node, Expert) and type(node).forward is Expert.forward:
            return self._expert(node)
        if kind is _ExecuteExpert:
            return self._execute()
        if kind is BetaMixer:
            self.draws = self.draws or 0.0 < node.beta < 1.0
            return self._mixer(node)
        return self._forward(node)

    def _forward(self, node: TensorDictModuleBase) -> _Step:
        """``node``'s own call on a TensorDict of every entry; its entries replace the dict's."""
        self.opaque = True
        batch_size = self.batch_size

        def step(values: Values) -> None:
            out = node(TensorDict(values, batch_size=batch_size))
            values.clear()
            values.update(out.items(include_nested=True, leaves_only=True))

        return step

    # -------------------------------------------------------------- the replays
    def _sequence(self, nodes: list[TensorDictModuleBase]) -> _Step:
        steps = [self._compile(n) for n in nodes]

        def step(values: Values) -> None:
            for s in steps:
                s(values)

        return step

    def _module(self, node: TensorDictModule) -> _Step:
        fn, in_keys, out_keys = (
            direct_call(node.module),
            list(node.in_keys),
            list(node.out_keys_source),
        )
        strict, batch_size = node.strict, self.batch_size

        def write(values: Values, out) -> None:
            # TensorDictModule.forward: the outputs, in the order of out_keys
            if isinstance(out, dict) and all(k in out for k in out_keys):
                out = tuple(out[k] for k in out_keys)
            if not isinstance(out, tuple):
                out = (out,)
            if len(out) != len(out_keys):
                raise RuntimeError(f"{len(out)} outputs for out_keys {out_keys}")
            for k, v in zip(out_keys, out):
                if k == "_":  # tensordict's placeholder for an output to drop
                    continue
                if not isinstance(v, torch.Tensor):  # written as tensordict writes it
                    v = TensorDict(batch_size=batch_size).set(k, TensorDict.from_any(v)).get(k)
                values[k] = v

        if len(in_keys) == 1 and len(out_keys) == 1 and out_keys[0] != "_":
            (key_in,), (key_out,) = in_keys, out_keys

            def one(values: Values) -> None:  # one tensor in, one out: the common case
                out = fn(values[key_in] if strict else values.get(key_in))
                if isinstance(out, torch.Tensor):
                    values[key_out] = out
                else:
                    write(values, out)

            return one

        def step(values: Values) -> None:
            # missing inputs are None unless strict
            write(values, fn(*(values[k] if strict else values.get(k) for k in in_keys)))

        return step

    def _replayable_actor(self, node: ProbabilisticActor) -> bool:
        """An actor of plain modules whose last module builds one distribution and writes
        one sample: greedy (DETERMINISTIC, MODE) or drawn (RANDOM). (Its hooks and private
        sampler settings: :func:`~imitrl.compat.plain_call`, asked by ``_compile``.)"""
        if self.exploration not in (
            ExplorationType.DETERMINISTIC, ExplorationType.MODE, ExplorationType.RANDOM,
        ):  # fmt: skip
            return False  # MEAN, MEDIAN: through its own forward
        *det, last = list(node.module)
        return (
            isinstance(last, ProbabilisticTensorDictModule)
            and (
                self.exploration is not ExplorationType.DETERMINISTIC
                or hasattr(last.distribution_class, "deterministic_sample")  # as _dist_sample
            )
            and isinstance(last.distribution_kwargs, dict)
            and len(last.dist_sample_keys) == 1
            and all(type(m) in (Module, TensorDictModule) for m in det)
        )

    def _actor(self, node: ProbabilisticActor) -> _Step:
        *det, last = list(node.module)
        params = self._sequence(det)
        dist_class, dist_kwargs = last.distribution_class, last.distribution_kwargs
        names = [k[-1] if isinstance(k, tuple) else k for k in last.dist_keys]
        in_keys, (out_key,) = list(last.in_keys), list(last.dist_sample_keys)
        exploration = self.exploration
        if exploration is ExplorationType.RANDOM:
            self.draws = True
            if categorical.replays(dist_class, names, dist_kwargs):
                (logits_key,) = in_keys

                def categorical_step(values: Values) -> None:
                    params(values)
                    # sample() without building the distribution (same bits, same draw)
                    values[out_key] = categorical.sample(values[logits_key])

                return categorical_step
        elif dist_class is GreedyCategorical and names == ["logits"] and not dist_kwargs:
            (logits_key,) = in_keys

            def greedy(values: Values) -> None:
                params(values)
                # its deterministic_sample (= mode), without building the distribution
                values[out_key] = GreedyCategorical.greedy(values[logits_key])

            return greedy

        if exploration is not ExplorationType.MODE and tanh_normal.replays(
            dist_class, names, dist_kwargs
        ):
            (loc_key, scale_key), draw = in_keys, exploration is ExplorationType.RANDOM
            action = tanh_normal.TanhNormalAction(dist_kwargs.get("low"), dist_kwargs.get("high"))

            def tanh_normal_step(values: Values) -> None:
                params(values)
                # rsample / deterministic_sample without the distribution (same bits)
                values[out_key] = action(values[loc_key], values[scale_key], draw=draw)

            return tanh_normal_step

        def step(values: Values) -> None:
            params(values)  # the network: writes the distribution's parameters
            # ProbabilisticTensorDictModule.get_dist, then _dist_sample
            dist = dist_class(**{n: values.get(k) for n, k in zip(names, in_keys)}, **dist_kwargs)
            if exploration is ExplorationType.RANDOM:  # the module's own draw, one sample
                values[out_key] = dist.rsample() if dist.has_rsample else dist.sample()
            elif exploration is ExplorationType.MODE:
                values[out_key] = dist.mode
            else:
                values[out_key] = dist.deterministic_sample

        return step

    def _expert(self, node: Expert) -> _Step:
        in_keys, batch_size = list(node.in_keys), self.batch_size
        own_label = type(node).label is Expert.label
        fn = direct_call(node.module)

        def step(values: Values) -> None:
            raw: object
            if own_label:  # Expert.label: the function of the in-keys
                raw = fn(*(values[k] for k in in_keys))
            else:  # a subclass's label reads a TensorDict of the in-keys
                raw = node.label(TensorDict({k: values[k] for k in in_keys}, batch_size))
            values[keys.EXPERT_ACTION] = node.cast_label(raw, batch_size)

        return step

    def _execute(self) -> _Step:
        batch_size = self.batch_size

        def step(values: Values) -> None:
            values[keys.ACTION], values[keys.EXPERT_EXECUTED] = _ExecuteExpert.execute(
                values[keys.EXPERT_ACTION], batch_size
            )

        return step

    def _mixer(self, node: BetaMixer) -> _Step:
        batch_size = self.batch_size

        def step(values: Values) -> None:
            learner, action, coin = node.mix(
                values[keys.EXPERT_ACTION], values.get(keys.ACTION), batch_size
            )
            values[keys.LEARNER_ACTION] = learner
            values[keys.ACTION] = action
            values[keys.EXPERT_EXECUTED] = coin

        return step
