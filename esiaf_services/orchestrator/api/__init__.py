"""The REST API: every router, its models, dependencies, auth, body limits, OpenAPI
document and the FastAPI app that mounts them.

May import anything in the orchestrator (``core`` for the running orchestrator a request uses,
through ``deps.get_core``). Nothing but ``server``, ``cli`` and the package's ``__init__``
imports ``api``.
"""
