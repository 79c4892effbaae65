"""Datasets (OpenPCDet's processed Waymo format, the synthetic default) and their transforms."""
