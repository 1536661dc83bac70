"""Robots: the catalog of named robots, load_robot() for a name or a URDF, SDF or MJCF file, and the checks that
untrusted robot files pass before Pinocchio builds them.

The modules, from the bottom: reading.py (untrusted files: limits, safe XML, allowed folders), entries.py (the
catalog's data), checks.py (what a description and its model must satisfy), srdf.py (named poses), sdformat.py
(SDF to URDF), mjcf.py (MuJoCo files), loading.py (load_robot and the geometry of a loaded robot).
"""

from .checks import SINGULAR_MASS_RATIO, SUPPORTED_JOINT_TYPES, check_urdf
from .entries import (
    CATALOG,
    DEFAULT_POSE_NAMES,
    ROBOT_PREFIX,
    CatalogEntry,
    catalog_srdf,
    catalog_urdf,
    default_pose_name,
    example_robot_data_share,
    shipped_models_dir,
)
from .loading import build_geometry, catalog_table, derived_urdf, load_robot, mesh_roots, reduce_configuration
from .mjcf import MJCF_SUFFIXES, check_mjcf
from .reading import (
    MAX_DOFS,
    MAX_JOINTS,
    MAX_LINKS,
    MAX_URDF_BYTES,
    MAX_XML_ELEMENTS,
    count_start_tags,
    folder_list,
    inside_roots,
    parse_urdf,
    parse_xml,
    read_urdf,
    read_xml_file,
    resolve_mesh_uri,
)

__all__ = [
    "CATALOG",
    "DEFAULT_POSE_NAMES",
    "MAX_DOFS",
    "MAX_JOINTS",
    "MAX_LINKS",
    "MAX_URDF_BYTES",
    "MAX_XML_ELEMENTS",
    "MJCF_SUFFIXES",
    "ROBOT_PREFIX",
    "SINGULAR_MASS_RATIO",
    "SUPPORTED_JOINT_TYPES",
    "CatalogEntry",
    "build_geometry",
    "catalog_srdf",
    "catalog_table",
    "catalog_urdf",
    "check_mjcf",
    "check_urdf",
    "count_start_tags",
    "default_pose_name",
    "derived_urdf",
    "example_robot_data_share",
    "folder_list",
    "inside_roots",
    "load_robot",
    "mesh_roots",
    "parse_urdf",
    "parse_xml",
    "read_urdf",
    "read_xml_file",
    "reduce_configuration",
    "resolve_mesh_uri",
    "shipped_models_dir",
]
