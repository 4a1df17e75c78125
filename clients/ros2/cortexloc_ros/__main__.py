"""`python -m cortexloc_ros`: the node, as `cortexloc-ros`."""

from cortexloc_ros.node import run

run()
