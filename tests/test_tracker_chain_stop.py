"""KLT's rest (klt_rest_after_losses) is refused with the chain's early stop (core/chain_links.enough_links:
chain_enough_verified, chain_stop_after_failures; TrackerParams.check): together they folded a strip of seneca_part's
replay (block check FAILED, 23.3/16.7 m from GPS: bench/results/real_surveys_6e10adb.jsonl); the early stop alone did
not (bench/results/real_surveys_tracker_chainstop_on_6c8d3df.jsonl) but is off by default (brighton 1.10-1.17x
further from GPS vertically)."""

from __future__ import annotations

import pytest

from photogram_ros.core.chain_links import enough_links
from photogram_ros.core.tracker import TrackerParams
from photogram_ros.errors import ConfigError
from photogram_ros.params import from_dict


def test_klt_rest_with_the_chain_stop_is_refused():
    for stop in ({'chain_enough_verified': 4}, {'chain_stop_after_failures': 3}):
        with pytest.raises(ConfigError, match='klt_rest_after_losses 3 with the chain'):
            from_dict(TrackerParams, {'klt_rest_after_losses': 3, **stop})
    # Each alone is allowed.
    from_dict(TrackerParams, {'klt_rest_after_losses': 3, 'chain_enough_verified': 0, 'chain_stop_after_failures': 0})
    from_dict(TrackerParams, {'chain_enough_verified': 4, 'chain_stop_after_failures': 3})


def test_the_early_stop_rule():
    assert from_dict(TrackerParams, {}).klt_rest_after_losses == 0
    p = from_dict(TrackerParams, {'chain_enough_verified': 4, 'chain_stop_after_failures': 3})
    # seneca_part's frame 16 (bench/tracker_chain_links.py): 4 of the 10 candidates verified, nearest first -> stop.
    assert not enough_links(3, 0, p) and enough_links(4, 0, p)
    # frame 29: 2 verified, then 3 in a row failed -> stop; before one verified, failures never stop it.
    assert not enough_links(2, 2, p) and enough_links(2, 3, p) and not enough_links(0, 9, p)
    off = from_dict(TrackerParams, {'chain_enough_verified': 0, 'chain_stop_after_failures': 0})
    assert not enough_links(40, 40, off)
