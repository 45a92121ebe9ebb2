"""User-supplied Mitsuba 3 XML scenes, rendered with their own camera but our buffers.

The scene's own integrator and film are ignored: every image goes through our split-buffer
integrator with a box-filtered film (``render.buffers.make_sensor``), at our sample counts, so a
production scene lands in the store exactly like a test frame of the random dataset.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import PipelineError


class ExternalSceneError(PipelineError, RuntimeError):
    """A Mitsuba scene file from the user cannot be rendered; the message names the file or what is missing."""


def load_external_scene(mi, xml: str):
    path = Path(xml)
    if not path.is_file():
        raise ExternalSceneError(f"{xml}: scene file not found")
    try:
        # Mitsuba resolves relative asset paths against the XML's folder.
        return mi.load_file(str(path.resolve()), parallel=False, optimize=False)  # fixed order: see render.scene
    except Exception as exc:  # Mitsuba raises RuntimeError with the parser's message
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise ExternalSceneError(f"{xml}: Mitsuba cannot load this scene: {first}") from None


def external_sensor(mi, scene, width: int | None, height: int | None):
    """A perspective sensor with the scene's first camera pose and field of view, our film."""
    from render.buffers import make_sensor

    sensors = scene.sensors()
    if not sensors:
        raise ExternalSceneError("the scene has no sensor (camera) to render from")
    sensor = sensors[0]
    params = mi.traverse(sensor)
    if "x_fov" not in params:
        raise ExternalSceneError(f"the scene's camera is a {type(sensor).__name__}; only perspective cameras are supported")
    size = sensor.film().size()
    w = width or int(size[0])
    h = height or int(size[1])
    matrix = np.asarray(params["to_world"].matrix.numpy(), dtype=np.float64).reshape(4, 4)
    to_world = mi.ScalarTransform4f(matrix)
    return make_sensor(mi, to_world, float(params["x_fov"][0]), w, h)
