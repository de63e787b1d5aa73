"""Sphinx configuration of the haptic_topology documentation (``make docs``).

The pages are MyST Markdown; the API reference is autodoc of the docstrings; the node parameter
tables are generated from the settings classes by ``_ext/haptic_params.py`` while the site
builds. ``make docs`` runs ``sphinx-build -W --keep-going -n``: every warning and every
unresolved cross-reference fails the build. No extension fetches anything over the network.
"""

from __future__ import annotations

import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / '_ext'))
sys.path.insert(0, str(HERE.parent))

import haptic_topology  # noqa: E402

project = 'haptic_topology'
author = 'haptic_topology contributors'
copyright = 'haptic_topology contributors, Apache License 2.0'
release = haptic_topology.__version__
version = release

extensions = [
    'myst_parser',
    'sphinx.ext.autodoc',
    'haptic_params',
    'haptic_cli',
    'haptic_equations',
]

source_suffix = {'.md': 'markdown', '.rst': 'restructuredtext'}
root_doc = 'index'
exclude_patterns = ['_build', 'Thumbs.db', '.DS_Store', 'img/**']
# foxglove.md belongs to the Foxglove page of another change; it joins the toctree there.
myst_heading_anchors = 3
# Quotes in this documentation are mostly YAML, shell and Python quoting (parameter descriptions
# too): keep them as typed.
smartquotes = False
myst_enable_extensions = ['colon_fence', 'deflist']

# Read the Docs' theme, the one rosdoc2 builds ROS package documentation with: its navigation
# stays beside the text down to 768 px wide (a laptop, a 1280 px window) and folds into a menu
# button below. It ships its files (jQuery through sphinxcontrib-jquery), so the build fetches
# nothing.
html_theme = 'sphinx_rtd_theme'
html_title = 'haptic_topology'
html_theme_options = {
    'collapse_navigation': False,
    'navigation_depth': 3,
    'titles_only': False,
}
html_static_path: list[str] = []

# -- autodoc -----------------------------------------------------------------------------------
autodoc_member_order = 'bysource'
autodoc_typehints = 'description'
autodoc_typehints_format = 'short'
autodoc_default_options = {'members': True, 'show-inheritance': True, 'ignore-module-all': True}
autodoc_preserve_defaults = True

# -- nitpicky: unresolved references are errors ------------------------------------------------
nitpicky = True
# Types of the standard library and of third-party packages: no inventory is fetched (the
# build is offline), so references to them cannot resolve. Only names outside this package
# are listed here; a reference into haptic_topology that does not resolve fails the build.
_STDLIB = (
    'abc', 'argparse', 'array', 'collections', 'concurrent', 'contextlib', 'dataclasses',
    'enum', 'gc', 'io', 'logging', 'multiprocessing', 'os', 'pathlib', 'queue', 'random',
    'selectors', 'signal', 'socket', 'subprocess', 'threading', 'time', 'types', 'typing',
    'xml', 'zlib',
)
_THIRD_PARTY = tuple(rf'{module}(\..*)?' for module in _STDLIB) + (
    r'numpy(\..*)?', r'np\..*', r'npt\..*', r'NDArray', r'ArrayLike', r'DTypeLike',
    r'pinocchio(\..*)?', r'pin\..*', r'coal(\..*)?', r'scipy(\..*)?', r'yaml(\..*)?',
    r'rclpy(\..*)?', r'mcap(\..*)?', r'rosbags(\..*)?', r'matplotlib(\..*)?',
    r'builtin_interfaces(\..*)?', r'std_msgs(\..*)?', r'geometry_msgs(\..*)?',
    r'sensor_msgs(\..*)?', r'diagnostic_msgs(\..*)?', r'visualization_msgs(\..*)?',
    r'tf2_msgs(\..*)?', r'rosgraph_msgs(\..*)?', r'lifecycle_msgs(\..*)?',
    r'haptic_topology_msgs(\..*)?', r'foxglove(\..*)?', r'websockets(\..*)?',
)
nitpick_ignore_regex = [(r'py:.*', pattern) for pattern in _THIRD_PARTY]
nitpick_ignore = [
    # multiprocessing.shared_memory.SharedMemory as autodoc prints it in a signature
    ('py:class', 'SharedMemory'),
    # A TypeVar (the settings class a classmethod returns) has no page to link to.
    ('py:class', 'haptic_topology.config.settings.S'),
]
