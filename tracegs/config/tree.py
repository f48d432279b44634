"""The config repository read explicitly: Hydra's config loader on a command's search path, with no global Hydra
state, so code that reads other configs of the tree (a Table 3 variant's sections, a stage option's file) runs
the same inside a command, in a test, or from Python with no Hydra context open.

A command records its search path in its config (``config_search_path``: the entry point from the Hydra app it
runs in, an in-process composition from the Hydra context it composes in); :meth:`ConfigTree.of` reads it back, so a lookup sees the
config files the command saw (a variant added in another config folder included). A config that records none
(built in Python) reads the package's tree (tracegs.location).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from hydra._internal.config_loader_impl import ConfigLoaderImpl
from hydra._internal.config_search_path_impl import ConfigSearchPathImpl
from hydra._internal.utils import create_config_search_path
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf, open_dict

from tracegs.location import CONF_DIR


@dataclass(frozen=True)
class ConfigTree:
    """The config files on one search path, each entry ``<provider>=<scheme>://<path>`` as Hydra lists its sources
    (the provider names Hydra's own configs, the app's, a plugin's or the structured schema)."""

    search_path: tuple[str, ...]

    @classmethod
    def at(cls, config_dir: str) -> ConfigTree:
        """The search path a Hydra app on ``config_dir`` reads (Hydra's own configs and its plugins' included)."""
        return cls(_app_search_path(config_dir))

    @classmethod
    def of(cls, cfg: DictConfig) -> ConfigTree:
        """The tree the command that composed ``cfg`` read (``cfg.config_search_path``); the package's tree for a
        config that records none (one built in Python)."""
        recorded = OmegaConf.select(cfg, "config_search_path", default=None)
        return cls(tuple(recorded)) if recorded else cls.at(CONF_DIR)

    def compose(self, config_name: str, overrides: Sequence[str] = ()) -> DictConfig:
        """``<config_name>.yaml`` under ``overrides``, composed as ``hydra.compose`` would (no ``hydra`` node); a
        new copy each call."""
        cfg = _loader(self.search_path).load_configuration(config_name, list(overrides), RunMode.RUN,
                                                           from_shell=False)
        with open_dict(cfg):
            del cfg["hydra"]
        return cfg

    def group_options(self, group: str) -> list[str]:
        """The options of config group ``group`` (its files, on every folder of the search path)."""
        return _loader(self.search_path).get_group_options(group)

    def option(self, group: str, name: str) -> dict[str, Any]:
        """Option ``name`` of group ``group`` as its file is written: interpolations unresolved, no defaults list."""
        loaded = _loader(self.search_path).repository.load_config(f"{group}/{name}")
        if loaded is None:
            raise FileNotFoundError(f"no config {group}/{name}.yaml on the search path {list(self.search_path)}")
        return OmegaConf.to_container(loaded.config, resolve=False)


def search_path_of(loader: Any) -> list[str]:
    """The search path a Hydra config loader reads (``GlobalHydra.instance().config_loader()`` where a command
    composes), as :class:`ConfigTree` entries."""
    return [f"{source.provider}={source.full_path()}" for source in loader.get_sources()]


@functools.lru_cache(maxsize=8)
def _app_search_path(config_dir: str) -> tuple[str, ...]:
    return tuple(search_path_of(ConfigLoaderImpl(create_config_search_path(config_dir))))


@functools.lru_cache(maxsize=8)
def _loader(search_path: tuple[str, ...]) -> ConfigLoaderImpl:
    explicit = ConfigSearchPathImpl()
    for entry in search_path:
        provider, _, path = entry.partition("=")
        explicit.append(provider, path)
    return ConfigLoaderImpl(explicit)
