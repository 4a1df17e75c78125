"""The front end (docs/design/science.md §6, §7): image bytes -> network input -> descriptor -> sLSBH code.

    images/      bytes -> (H, W, 3) uint8 RGB -> (N, 3, 224, 224) float32: limits, header parsers, decode
    backbones/   registry of networks, (N, 3, 224, 224) -> (N, D) L2-normalised descriptors
    weights.py   the AlexNet checkpoint: download, import, check, trim, cache
    slsbh/       projection (D, k) and hashing (N, k) -> (N, 2n) sorted active columns
    adaptation.py  a stream's running mean subtracted in projection space
    embedding.py Embedder, the one entry point: bytes -> features or codes
"""
