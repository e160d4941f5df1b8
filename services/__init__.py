"""The scanflow services: thin Zenoh shells (one process each) around the core library."""
