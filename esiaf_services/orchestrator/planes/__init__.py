"""The planes: the orchestrator's ZeroMQ sockets and what flows through them.

Owns the control plane (control: registrations' heartbeats, state pushes, acks), the results
plane (results: its socket loop; ingest: the pipeline that stores, fuses and publishes each
batch in one transaction, retrying the store; clocks: each stream's reference time and clock
offset), the fan-out to websocket clients (hub), ZeroMQ authentication (zap), the proof that a
message comes from its registration (binding), the result codec (codec), the latency
histograms the pipeline observes (metrics), and each stream's player: its orders and barge-ins
(players).

May import: the standard library, ``esiaf``, ``settings``, ``fusion``, ``registry`` and
``store``. Never ``api`` or ``core``.
"""
