"""The API's routers, one per resource: ``jobs``, ``schema`` (spec schema and OpenAPI docs), ``health``,
``dashboard``; ``common`` holds what they share (authentication, the job manager)."""
