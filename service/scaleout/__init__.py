"""The scale-out on Ray Serve (docs/scaling.md; docs/design/service.md §9): map shards, an encoder
deployment and an ingress that serves the same `/v1` API. `deployments` imports Ray (the `ray` extra);
the rest does not."""
