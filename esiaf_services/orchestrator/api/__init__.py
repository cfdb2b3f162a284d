"""The REST and websocket API: one router per resource."""
