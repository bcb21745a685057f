"""The job spec (:mod:`.model`: one pydantic model, its JSON Schema published by the API) and its regions on the
grids, approximated from inside (targets, safe sets) or outside (avoid sets), with exact counts (:mod:`.regions`,
docs/method.md §1)."""
