"""The Zenoh router the other services connect to (a Python session in router mode)."""
