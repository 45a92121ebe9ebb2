"""Stage 1: the dataset: random scenes, rendered by a split-buffer Mitsuba integrator into the store.
``python -m pipeline`` dispatches here for ``dataset``, ``render-scene``, ``plan`` and ``bench``.

- ``render.scene``: the scene randomizer (a scene as a JSON description; ``build_scene`` and
  ``build_sensor`` make it a Mitsuba scene and camera).
- ``render.geometry``, ``render.materials``, ``render.textures``, ``render.lights``,
  ``render.camera``: its parts: random shapes as meshes, BSDFs, procedural textures, lights set
  by target irradiance, a smooth camera move over the frames (and the orbit, dolly and
  camera-to-camera paths of a user's scene).
- ``render.rounding``: the rounding of a description's numbers, shared by every generator.
- ``render.layout``: object placement, the ground and a room's walls, shared with the stress presets.
- ``render.interior``: furnished interiors (``scene.interior_probability``): ``render.room`` draws
  their floor plans and walls, ``render.furniture`` the furniture, lamps and props assembled from
  primitives, ``render.palette`` the materials of rooms and products (wood, fabric, metal, glass).
- ``render.product``: product shots (``scene.product_probability``): products on a sweep or a table
  under softboxes and strip lights.
- ``render.stress``: named extreme scenes in the same description format (``dataset.stress``).
- ``render.integrator``: the split-buffer path tracer: every buffer of ``pipeline.schema`` in one pass.
- ``render.buffers``: one image rendered into per-buffer means and variances of the mean; the
  box-filtered camera every buffer uses.
- ``render.progressive``: a ground truth rendered in passes up to a target PSNR.
- ``render.frame``: one frame (the unit of work, in a worker or a Ray task) into the store: GT1,
  GT2 and the low-spp stacks, from a random scene or a user's XML.
- ``render.dataset``: the dataset stage (``make dataset``): plan scenes and frames, run the
  missing ones, write the manifests.
- ``render.external``: a user's Mitsuba scene into the store's ``external`` split (``render-scene``),
  one frame or a sequence along a camera path.
- ``render.plan``: what a config costs before anything runs (``plan``).
- ``render.bench``: the dataset stage's performance claims, measured (``make bench``).
"""
