"""Scene folders: in-memory records, reading and writing (docs/dataset_format.md), synthetic scenes, PLY."""
