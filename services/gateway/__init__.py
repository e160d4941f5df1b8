"""HTTP gateway: FastAPI over the Zenoh bus (pose queries, match, maps, health, ingest, stream).

It holds no algorithm: requests become Zenoh subscriptions, queries and publications.
"""
