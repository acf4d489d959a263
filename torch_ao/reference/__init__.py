"""Ray-traced references: scenes, a batched torch tracer (optional Embree for meshes), G-buffers,
ground-truth AO with standard errors and one-bounce indirect light for the same views."""
from .embree import embree_available
from ..io.mesh import frame_view, gltf_camera, load_mesh_file, mesh_scene
from .render import Reference, default_views, render_reference
from ..scene import Box, Cylinder, Light, LookAt, Mesh, Plane, Scene, Sphere, rotation_from_axis_angle, rotation_y
from .scenes import MESH_DIR, MESH_SCENES, SCENES, get_scene, icosphere, list_scenes, scene_unavailable, torus
from .tracer import TORCH_MAX_TRIANGLES, Hit, Tracer
from .views import Views, look_at, look_at_matrix

__all__ = [
    "Scene", "Plane", "Sphere", "Box", "Cylinder", "Mesh", "Light", "LookAt", "rotation_y", "rotation_from_axis_angle",
    "SCENES", "MESH_SCENES", "MESH_DIR", "get_scene", "list_scenes", "scene_unavailable", "icosphere", "torus",
    "Tracer", "Hit", "TORCH_MAX_TRIANGLES", "embree_available",
    "Views", "look_at", "look_at_matrix",
    "Reference", "render_reference", "default_views",
    "load_mesh_file", "mesh_scene", "frame_view", "gltf_camera",
]
