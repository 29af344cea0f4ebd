"""Fixtures of the Hub tests: a dataset's cache and the repository a test Hub serves."""

from tests._hub_child import hub_env, repo  # noqa: F401  (fixtures, found by name)
