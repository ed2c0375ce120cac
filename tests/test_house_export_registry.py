"""The export products are one module each behind one registry (io/products/): the command offers the registry's
names, export_map runs the chosen ones in the registry's order with each intermediate made once, and an unknown
name is refused before anything is written."""

from __future__ import annotations

import pytest


def test_one_module_per_product_and_the_command_offers_the_registry():
    from photogram_ros.commands.export import PRODUCTS as COMMAND_PRODUCTS
    from photogram_ros.io.products import PRODUCTS, product_names
    assert [p.key for p in PRODUCTS] == ['las', 'laz', 'ply', 'dsm', 'dtm', 'contours', 'ortho']
    assert COMMAND_PRODUCTS == product_names() == ('las', 'laz', 'ply', 'dsm', 'dtm', 'ortho')
    modules = {p.write.__module__ for p in PRODUCTS}
    assert modules == {f'photogram_ros.io.products.{m}' for m in ('clouds', 'dsm', 'dtm', 'contours', 'ortho')}


def test_the_plan_names_each_step_once_in_order():
    from photogram_ros.io.products import PRODUCTS, plan
    by = {p.key: p for p in PRODUCTS}
    assert plan([by[k] for k in ('las', 'laz', 'ply', 'dsm', 'dtm', 'contours', 'ortho')]) == [
        'cloud', 'LAS', 'LAZ', 'PLY', 'DSM', 'DTM', 'contours', 'ortho']
    assert plan([by['ortho']]) == ['cloud', 'DSM', 'ortho']
    assert plan([by['contours']]) == ['cloud', 'DSM', 'DTM', 'contours']
    assert plan([]) == ['cloud']


def test_an_unknown_product_is_refused_before_anything_is_written(tmp_path):
    from photogram_ros.errors import ConfigError
    from photogram_ros.io.export import export_map
    with pytest.raises(ConfigError, match=r"unknown products \['tiff'\]; choose from \['las'"):
        export_map(tmp_path / 'no_map', tmp_path / 'out', 'EPSG:32632', products=('dsm', 'tiff'))
    with pytest.raises(ConfigError, match='contour interval must be positive'):
        export_map(tmp_path / 'no_map', tmp_path / 'out', 'EPSG:32632', contour_interval_m=-1.0)
    assert not (tmp_path / 'out').exists()
