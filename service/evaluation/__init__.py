"""The experiments that run the service's own path (docs/results.md §9): no re-implementation, the map's
configuration resolved as a created map's and every frame through `models.pipeline.observe`.

    service_path.py  learn a database traverse, localise a query traverse (`--methods service`,
                     `service-without-tm`), scored per query; the operating point of a precision
    revisit.py       corridor-like revisits: the same frames again with pixel noise
    unknown.py       false revisits on places never stored, and the decision on the places stored
    runtime_parity.py  the backbone's runtimes (torch, ONNX Runtime) give the same codes and answers
    resize.py        crop or squash on frames of several shapes cut from the same footage

The pure measures (metrics, datasets, the other methods) are `models.evaluation`'s; the command line of
all of them is `cortexloc eval` (service/cli/evaluate.py, typer).
"""
