"""``peer_imitation.py``'s parts: ``tasks`` (the task table, shared by both sides as
JSON), ``imitrl_run`` (one imitrl run, a child process in this venv), ``peer_run`` (one
imitation run, a child process in the peer's venv; it imports nothing from this
repository), ``runs`` (launching the children, the expert check), ``report``
(medians, ratios, tables)."""
