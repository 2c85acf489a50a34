"""Blur formation (docs/method.md §4): the settings (config), how many virtual views a render uses
(views), the virtual poses and sub-frame times of an exposure (virtual_poses), the blurred render
(render), the exposure length (exposure) and the endpoint models (endpoints)."""
