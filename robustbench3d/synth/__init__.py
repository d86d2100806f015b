"""Embedded default dataset: procedural driving scenes written in the KITTI layout."""
