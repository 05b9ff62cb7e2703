"""The edge capture agent: a client that streams frames from a rig to the gateway.

It reads captures with `pipeline.io.capture_io` and talks to the REST API; its streaming
protocol is not defined yet.
"""
