"""The sample capture `volumesh serve --sample` stores: a synthetic 8-camera snowman."""

from __future__ import annotations

import hashlib
import tempfile
from pathlib import Path

from workers.settings import Settings

SAMPLE_NAME = "sample-capture.zip"


def build_sample_zip(path: Path) -> None:
    """Synthesise the built-in subject with the default rig and pack it as a capture zip."""
    from pipeline.io.capture_io import write_capture, zip_capture
    from pipeline.synth.scene import SynthConfig, sample_mesh, synthesize

    meta, views, _ = synthesize(sample_mesh(), SynthConfig(seed=0))
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        write_capture(Path(tmp) / "capture", meta, views)
        zip_capture(Path(tmp) / "capture", Path(tmp) / SAMPLE_NAME)
        (Path(tmp) / SAMPLE_NAME).replace(path)


def store_sample(settings: Settings) -> str:
    """Make sure the sample is stored and ready; returns its capture id."""
    from pipeline.io.capture_io import open_capture
    from workers.db import init_db, make_engine, make_sessionmaker
    from workers.models import Capture
    from workers.storage import make_storage

    path = settings.data_dir / SAMPLE_NAME
    if not path.is_file():
        build_sample_zip(path)
    sha256 = hashlib.sha256(path.read_bytes()).hexdigest()
    capture_id = sha256[:32]
    engine = make_engine(settings)
    init_db(engine)
    with make_sessionmaker(engine)() as session:
        row = session.get(Capture, capture_id)
        if row is not None and row.state == "ready":
            return capture_id
        with open_capture(path) as reader:  # the same validation an upload gets
            cameras, frames = len(reader.meta.cameras), len(reader.meta.frames)
        key = f"captures/{sha256}.zip"
        make_storage(settings).put_file(key, path)
        if row is None:
            row = Capture(id=capture_id, sha256=sha256, size_bytes=path.stat().st_size,
                          storage_key=key)
            session.add(row)
        row.state, row.cameras, row.frames, row.error = "ready", cameras, frames, None
        session.commit()
    engine.dispose()
    return capture_id
