"""The registry: pure logic, no I/O.

Owns the components the orchestrator knows (alive, departed, their instances, keys and stream
assignments: components), how a replicated service's streams go to its instances (assignment),
which audio format each link uses (negotiation), and when a stream has ended (streams).

May import: the standard library and ``esiaf``. Never ``store``, ``planes``, ``api`` or ``core``.
"""
