"""HTTP API (FastAPI): routes, schemas, auth, the operator page. Talks to ``cell`` only
(and ``estimator.transforms`` for pose JSON), never to ``drivers``."""
