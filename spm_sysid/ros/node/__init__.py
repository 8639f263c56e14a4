"""The parts of ``sysid_node``, each its own class: the node only wires them.

:mod:`.parameters` (declared from the schema, checked once, held),
:mod:`.recording` (messages into the buffer), :mod:`.identification` (jobs in
the worker process), :mod:`.publishing` (the model on its latched topics),
:mod:`.online` (prediction, validity, tracking) and :mod:`.reidentify` (the
automatic policy).
"""
