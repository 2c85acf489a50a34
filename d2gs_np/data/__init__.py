"""Scene folders: in-memory records, reading and writing (DATASET_FORMAT.md), synthetic scenes, PLY."""
