"""Images to a map's projected features (docs/design/service.md §1.1, §6): the embedders by backbone
(embedders.py), the bounded pool that batches every image (pool.py), and a map's projection, dense or
very sparse within the map's budget (projection.py)."""
