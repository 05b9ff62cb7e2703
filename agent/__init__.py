"""The edge capture agent (`volumesh agent`): frame-sets from a rig, recordings, a capture or
the synthetic rig, spooled on disk and sent to the gateway as a stream (docs/api.md,
"Streams").

An HTTP client: it imports pipeline for reading and encoding, never app or workers.

    sources, source_*   where frame-sets come from (open_source)
    capture             the capture loop: source -> framesets -> spool, with previews
    framesets           one frame-set as the stream's zip
    spool               frame-sets on disk until acknowledged, and the resumable state
    sender, gateway     the HTTP side: PUT with retries, create/close the stream
    run                 start to end (run_agent); stats: counters and the status line
    preview             preview.bin (volumesh.preview/1)
"""
