"""HTTP API (FastAPI): routes, schemas, auth, the operator page. Talks to ``cell`` only."""
