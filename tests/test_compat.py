"""imitrl.compat: each private fast path gives the public path's digits, and is live."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.data import LazyTensorStorage, ReplayBuffer
from torchrl.modules import ValueOperator

from imitrl import keys
from imitrl.compat import DirectWriteMixin, set_writer_cursor, writer_cursor
from imitrl.data import DemonstrationBuffer
from imitrl.policies.modules import Module, Value


def _obs_batch(n: int = 32, d: int = 5, seed: int = 0) -> TensorDict:
    g = torch.Generator().manual_seed(seed)
    return TensorDict({keys.OBSERVATION: torch.randn(n, d, generator=g)}, [n])


def _net(d_in: int = 5, d_out: int = 3, seed: int = 0) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(d_in, 16), nn.Tanh(), nn.Linear(16, d_out))


class _LocScale(nn.Module):
    """Two outputs, for multi-key writes: ``loc [N, 2]``, ``scale [N, 2]``."""

    def __init__(self) -> None:
        super().__init__()
        self.body = _net(5, 4, seed=1)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        loc, raw = self.body(x).chunk(2, dim=-1)
        return loc, nn.functional.softplus(raw)


def _assert_same_tensordict(a: TensorDict, b: TensorDict) -> None:
    assert set(a.keys(True, True)) == set(b.keys(True, True))
    for key in a.keys(True, True):
        assert torch.equal(a.get(key), b.get(key)), key


# ------------------------------------------------------------ DirectWriteMixin
def test_module_outputs_equal_a_plain_tensordict_module():
    net = _net()
    ours = Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])
    plain = TensorDictModule(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])
    a, b = ours(_obs_batch()), plain(_obs_batch())
    _assert_same_tensordict(a, b)
    assert a.get(keys.LOGITS).requires_grad and b.get(keys.LOGITS).requires_grad


def test_module_multi_output_and_dropped_output_equal_the_plain_path():
    net = _LocScale()
    for out_keys in ([keys.LOC, keys.SCALE], [keys.LOC, "_"], [("head", "loc"), "scale"]):
        ours = Module(net, in_keys=[keys.OBSERVATION], out_keys=out_keys)
        plain = TensorDictModule(net, in_keys=[keys.OBSERVATION], out_keys=out_keys)
        _assert_same_tensordict(ours(_obs_batch()), plain(_obs_batch()))


def test_value_outputs_equal_a_plain_value_operator():
    net = _net(d_out=1)
    ours = Value(net, in_keys=[keys.OBSERVATION])
    plain = ValueOperator(net, in_keys=[keys.OBSERVATION])
    assert ours.out_keys == plain.out_keys == [keys.STATE_VALUE]
    _assert_same_tensordict(ours(_obs_batch()), plain(_obs_batch()))


def test_fallback_paths_equal_the_plain_path():
    net = _net()
    for inplace in (False, "empty"):  # not written in place: tensordict's own writer
        ours = Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS], inplace=inplace)
        plain = TensorDictModule(
            net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS], inplace=inplace
        )
        _assert_same_tensordict(ours(_obs_batch()), plain(_obs_batch()))
    ours = Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])
    plain = TensorDictModule(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])
    out_a, out_b = TensorDict(batch_size=[32]), TensorDict(batch_size=[32])
    ours(_obs_batch(), tensordict_out=out_a)
    plain(_obs_batch(), tensordict_out=out_b)
    _assert_same_tensordict(out_a, out_b)


def test_output_count_mismatch_fails_like_tensordict():
    net = _net()
    for cls in (Module, TensorDictModule):
        module = cls(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS, keys.LOC])
        with pytest.raises(RuntimeError):
            module(_obs_batch())


def test_the_fast_path_is_live(monkeypatch):
    # If tensordict renames the private writer, the override silently stops running
    # (same digits, slow again): this test is the one that notices.
    assert "_write_to_tensordict" in vars(TensorDictModule)
    assert Module._write_to_tensordict is DirectWriteMixin._write_to_tensordict
    assert Value._write_to_tensordict is DirectWriteMixin._write_to_tensordict
    calls = []
    from_any = TensorDict.from_any

    def counting(cls, obj, *args, **kwargs):
        calls.append(type(obj))
        return from_any(obj, *args, **kwargs)

    monkeypatch.setattr(TensorDict, "from_any", classmethod(counting))
    net = _net()
    Module(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])(_obs_batch())
    assert calls == []
    TensorDictModule(net, in_keys=[keys.OBSERVATION], out_keys=[keys.LOGITS])(_obs_batch())
    assert calls == [torch.Tensor]  # the probing the fast path skips


# ----------------------------------------------------------- writer cursor
def _plain_rb(capacity: int) -> ReplayBuffer:
    return ReplayBuffer(storage=LazyTensorStorage(capacity))


def _items(n: int, start: int = 0) -> TensorDict:
    return TensorDict({"x": torch.arange(start, start + n)}, [n])


def test_writer_cursor_reads_what_the_public_state_dict_says():
    rb = _plain_rb(6)
    assert writer_cursor(rb) == 0
    written = 0
    for n in (2, 3, 1, 4):  # the last extend wraps the round-robin writer
        rb.extend(_items(n, written))
        written += n
        assert writer_cursor(rb) == rb.writer.state_dict()["_cursor"] == written % 6
        assert writer_cursor(rb) == len(rb) % 6 or len(rb) == 6


def test_set_writer_cursor_equals_the_public_state_dict_load():
    ours, public = _plain_rb(8), _plain_rb(8)
    for rb in (ours, public):
        rb.extend(_items(6))
    set_writer_cursor(ours, 2)
    public.writer.load_state_dict({"_cursor": 2})
    index_a, index_b = ours.extend(_items(3, 100)), public.extend(_items(3, 100))
    assert torch.equal(index_a, torch.arange(2, 5)) and torch.equal(index_a, index_b)
    assert writer_cursor(ours) == writer_cursor(public) == 5
    assert ours.write_count == public.write_count == 9  # the write count is untouched
    assert torch.equal(ours[:6]["x"], public[:6]["x"])
    assert ours[:6]["x"].tolist() == [0, 1, 100, 101, 102, 5]


# ------------------------------------ DemonstrationBuffer, the cursor's one user
def _rows(n: int, first_episode: int, *, nan: bool = False) -> TensorDict:
    """``n`` rows, one episode of ``n`` steps; ``nan=True`` poisons the reward."""
    a = torch.arange(n) % 4
    reward = torch.zeros(n, 1)
    if nan:
        reward[-1] = float("nan")
    return TensorDict(
        {
            keys.OBSERVATION: torch.arange(n) % 16,
            keys.EXPERT_ACTION: a,
            keys.ACTION: a.clone(),
            keys.EXPERT_EXECUTED: torch.ones(n, dtype=torch.bool),
            keys.EPISODE: torch.full((n,), first_episode),
            keys.ROUND: torch.zeros(n, dtype=torch.int64),
            keys.STEP: torch.arange(n),
            (keys.NEXT, keys.REWARD): reward,
        },
        [n],
    )


def test_extend_after_an_exactly_full_storage_lands_after_the_old_rows():
    buf = DemonstrationBuffer(capacity=8)
    first = _rows(8, 0)
    assert torch.equal(buf.extend(first), torch.arange(8))
    # torchrl's writer has wrapped: left alone, the next extend would overwrite row 0.
    assert len(buf) == 8 and writer_cursor(buf._rb) == 0
    index = buf.extend(_rows(5, buf.next_episode))
    assert torch.equal(index, torch.arange(8, 13))
    assert len(buf) == 13 and writer_cursor(buf._rb) == 13
    assert torch.equal(buf.data[:8][keys.OBSERVATION], first[keys.OBSERVATION])
    assert buf.data[keys.EPISODE].tolist() == [0] * 8 + [1] * 5


@pytest.mark.parametrize("filled", [7, 8])  # room left / the writer's cursor wrapped
def test_a_rejected_extend_changes_nothing_and_the_next_lands_after_the_old_rows(filled):
    buf = DemonstrationBuffer(capacity=8)
    buf.extend(_rows(filled, 0))
    before = buf.data.clone()
    cursor, capacity = writer_cursor(buf._rb), buf.capacity
    bad = [
        _rows(5, buf.next_episode, nan=True),  # NaN reward
        _rows(5, 0),  # episode id already used
        _rows(5, buf.next_episode).exclude(keys.STEP),  # missing key
    ]
    for rows in bad:
        with pytest.raises(ValueError):
            buf.extend(rows)
        assert len(buf) == filled and buf.capacity == capacity
        assert writer_cursor(buf._rb) == cursor
        _assert_same_tensordict(buf.data, before)
    index = buf.extend(_rows(5, buf.next_episode))
    assert torch.equal(index, torch.arange(filled, filled + 5))
    _assert_same_tensordict(buf.data[:filled], before)
    assert len(buf) == filled + 5 == writer_cursor(buf._rb)


def test_a_reloaded_full_buffer_extends_after_its_old_rows(tmp_path):
    buf = DemonstrationBuffer(capacity=8)
    buf.extend(_rows(8, 0))
    loaded, _ = DemonstrationBuffer.load(buf.save(tmp_path / "ckpt"))
    # a loaded buffer is exactly full: its writer has wrapped, like the saved one
    assert writer_cursor(loaded._rb) == writer_cursor(buf._rb) == 0
    index = loaded.extend(_rows(3, loaded.next_episode))
    assert torch.equal(index, torch.arange(8, 11))
    _assert_same_tensordict(loaded.data[:8], buf.data)


# ------------------------------------------------- the private queries compat.py makes
def test_the_hook_queries_see_each_public_registration():
    from imitrl.compat import forward_hooked, global_module_hooks, hooked

    for register in ("register_forward_hook", "register_forward_pre_hook",
                     "register_full_backward_hook", "register_full_backward_pre_hook"):  # fmt: skip
        m = nn.Linear(2, 2)
        assert not hooked(m) and not forward_hooked(m)
        handle = getattr(m, register)(lambda *a: None)
        assert hooked(m)
        assert forward_hooked(m) == ("forward" in register)
        handle.remove()
        assert not hooked(m)
    assert not global_module_hooks()
    handle = nn.modules.module.register_module_forward_hook(lambda *a: None)
    try:
        assert global_module_hooks()
    finally:
        handle.remove()
    assert not global_module_hooks()


def test_the_optimizer_hook_query_sees_its_own_and_global_hooks():
    from torch.optim.optimizer import (
        register_optimizer_step_post_hook,
        register_optimizer_step_pre_hook,
    )

    from imitrl.compat import optimizer_hooked

    opt = torch.optim.Adam(nn.Linear(2, 2).parameters())
    assert not optimizer_hooked(opt)
    for register in (
        opt.register_step_pre_hook,
        opt.register_step_post_hook,
        register_optimizer_step_pre_hook,
        register_optimizer_step_post_hook,
    ):
        handle = register(lambda *a: None)
        assert optimizer_hooked(opt)
        handle.remove()
        assert not optimizer_hooked(opt)


def test_the_foreach_kernels_equal_their_loops():
    from imitrl import compat

    g = torch.Generator().manual_seed(0)
    xs = [torch.randn(5, generator=g), torch.randn(3, 2, generator=g)]
    ys = [torch.randn_like(x) for x in xs]
    norms = compat.foreach_norm(xs, 2.0)
    assert all(torch.equal(n, torch.linalg.vector_norm(x, 2.0)) for n, x in zip(norms, xs))
    for name, loop in (
        ("foreach_add_", lambda x, y: x.add_(1)),
        ("foreach_mul_", lambda x, y: x.mul_(0.5)),
        ("foreach_copy_", lambda x, y: x.copy_(y)),
        ("foreach_lerp_", lambda x, y: x.lerp_(y, 0.25)),
    ):
        a, b = [x.clone() for x in xs], [x.clone() for x in xs]
        arg = {"foreach_add_": (1,), "foreach_mul_": (0.5,), "foreach_copy_": (ys,),
               "foreach_lerp_": (ys, 0.25)}[name]  # fmt: skip
        getattr(compat, name)(a, *arg)
        for x, y in zip(b, ys):
            loop(x, y)
        assert all(torch.equal(u, v) for u, v in zip(a, b)), name


def test_loss_mask_keys_and_validate_args_read_what_the_public_api_set():
    from torchrl.objectives import ClipPPOLoss

    from imitrl.compat import loss_mask_keys, validates_args
    from imitrl.learners import TaskSpec, build

    learner = build("default", TaskSpec.from_specs(3, 2), value=True)
    loss = ClipPPOLoss(learner.policy, learner.value)
    # the entry a TorchRL collector writes to mark padded steps masks the loss
    assert ("collector", "mask") in loss_mask_keys(loss)
    assert validates_args(torch.distributions.Normal(0.0, 1.0, validate_args=True))
    assert not validates_args(torch.distributions.Normal(0.0, 1.0, validate_args=False))
