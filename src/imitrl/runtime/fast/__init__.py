"""Accelerated paths: each gives the digits of its reference on public TorchRL/torch.

Reached only through the seam, :mod:`imitrl.runtime.paths` (``tests/runtime/test_paths.py``
greps that nothing else imports this package, and runs every piece against its
reference): ``env_steps`` (envs stepped directly), ``policy_call`` (a policy on a dict of
tensors, networks without hook bookkeeping), ``stepper`` (the two together, for the one
rollout loop), ``toy_text`` (evaluations of toy-text envs without a step loop),
``tensor_chain`` (a loss's networks on a batch's tensors), ``adam_step`` (Adam's update
without its per-call wrapper, on the CPU).
"""
