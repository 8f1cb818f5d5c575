"""Scenes: author a Mitsuba scene from a mesh, or load any Mitsuba XML.

- :mod:`.meshes`: read a mesh file, find what colours its surface, write it as PLY.
- :mod:`.authoring`: a scene XML around a mesh (:func:`scene_from_mesh`).
- :mod:`.loading`: any Mitsuba scene as a :class:`Scene` (:func:`load_scene`).
- :mod:`.probes`: rays into a loaded scene: first hits, room or object.
- :mod:`.upaxis`: the up axis a mesh's shape shows.
"""

from .authoring import LOOKS, UP_AXES, SceneOptions, authoring_notes, scene_from_mesh
from .loading import Scene, content_hash, load_scene, referenced_files, scene_from_mitsuba
from .meshes import DEFAULT_COLOR, MESH_SUFFIXES, load_mesh, normalise_vertices, write_ply

__all__ = ["DEFAULT_COLOR", "LOOKS", "MESH_SUFFIXES", "UP_AXES", "Scene", "SceneOptions", "authoring_notes",
           "content_hash", "load_mesh", "load_scene", "normalise_vertices", "referenced_files",
           "scene_from_mesh", "scene_from_mitsuba", "write_ply"]
