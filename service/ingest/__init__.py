"""`cortexloc ingest`: post a folder of images or a recorded ROS bag to a map, in source order.

- `service.ingest.sources`: the readers (image folder, ROS 1 `.bag`, ROS 2 bag via `rosbags`) that turn a
  source into `Frame`s (bytes to post, media type, stamp);
- `service.ingest.poster`: the HTTP side, one code path for a running service (`--url`) and the app run in
  this process (httpx's ASGI transport around the app's lifespan): map check, ordered posts, retries on 503,
  per-frame records and the summary;
- the typer command is `service.cli.ingest` (the command line is one package).

The ingest is a client of the HTTP API: it imports nothing of the runtime or the stores.
"""
