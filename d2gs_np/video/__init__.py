"""Video or image folder -> scene folder: decoding, SfM, which tracks are the static world, motion masks, the importer (docs/dataset_format.md §8)."""
