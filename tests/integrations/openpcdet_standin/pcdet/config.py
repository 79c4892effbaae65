"""OpenPCDet's ``pcdet/config.py`` interfaces: the global ``cfg`` and how YAML and ``--set``
pairs merge into it (``_BASE_CONFIG_`` read from the working directory, as OpenPCDet does)."""

from ast import literal_eval
from pathlib import Path

import yaml
from easydict import EasyDict


def cfg_from_list(cfg_list, config):
    """KEY VALUE pairs into ``config``; every key must exist; values by ``literal_eval``, else
    strings."""
    if len(cfg_list) % 2:
        raise ValueError(f"KEY VALUE pairs expected, got {cfg_list}")
    for key, text in zip(cfg_list[0::2], cfg_list[1::2]):
        *parents, last = key.split(".")
        node = config
        for sub in parents:
            node = node[sub]
        if last not in node:
            raise KeyError(f"NotFoundKey: {key}")
        try:
            node[last] = literal_eval(text)
        except (ValueError, SyntaxError):
            node[last] = text


def merge_new_config(config, new_config):
    if "_BASE_CONFIG_" in new_config:
        with open(new_config["_BASE_CONFIG_"]) as f:
            config.update(EasyDict(yaml.safe_load(f)))
    for key, value in new_config.items():
        if not isinstance(value, dict):
            config[key] = value
            continue
        if key not in config:
            config[key] = EasyDict()
        merge_new_config(config[key], value)
    return config


def cfg_from_yaml_file(cfg_file, config):
    with open(cfg_file) as f:
        merge_new_config(config=config, new_config=yaml.safe_load(f))
    return config


cfg = EasyDict()
cfg.ROOT_DIR = Path(__file__).resolve().parent.parent
cfg.LOCAL_RANK = 0
