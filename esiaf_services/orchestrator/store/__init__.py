"""The store: everything that lives in the SQLite database.

Owns the schema and its migrations (schema), the connection, its transactions and the write
queue (database), the repair of a damaged file (recover), the warm start of fusion state from
the database (warmstart), and the enrolled voices table (voices).

May import: the standard library, ``esiaf``, the orchestrator's ``settings``, and the pure
``fusion`` and ``registry`` packages (the types it stores and restores). Never ``planes``,
``api`` or ``core``.
"""
