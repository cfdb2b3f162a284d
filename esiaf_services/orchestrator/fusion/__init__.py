"""Fusion: pure logic, no I/O.

Owns how results of one stream are joined into fused results: the engine that opens, completes,
times out and revises fusions (engine), which results cover a span (coverage), the aggregates of
labels and directions (aggregate), the learnt latencies that set timeouts (latency), what a
dead instance left unanswered (orphans), and what the robot played and which utterances are its own
voice (playback).

May import: the standard library, ``esiaf``, and the orchestrator's ``settings``. Never
``store``, ``planes``, ``api`` or ``core``: it neither reads sockets nor writes the database.
"""
