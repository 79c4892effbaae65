"""A stand-in for OpenPCDet (``pcdet``) for tests/integrations/test_openpcdet.py: OpenPCDet's
compiled CUDA ops do not build on CI.

It holds what ``pcdet_atlas.integrations.openpcdet`` touches, at OpenPCDet's module paths, with
the names and signatures of open-mmlab/OpenPCDet at commit
8cacccec11db6f59bf6934600c9a175dae254806 (v0.6.0; the test checks them against a table taken
from that commit's source). The bodies are small CPU versions of what OpenPCDet's do there: the
Waymo infos, sampling, frame reading and sequence stacking, prediction dicts and collation as
OpenPCDet's; no data augmentor, point feature encoder or data processor (points reach the model
as read); ``load_data_to_gpu`` makes CPU tensors; the one detector, ``PointCountOracle``, is
not OpenPCDet's and stands for "any architecture".
"""

__version__ = "0.6.0+standin"
