"""Unit tests of the ros2 service's mapping (no DDS, no sockets)."""
