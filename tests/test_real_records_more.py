"""The other half of tests/test_real_records.py's whole-record checks (every other real record of the data
folder), in a module of its own so that pytest-xdist runs the two halves on two workers."""
from __future__ import annotations

import pytest
from test_real_records import RECORDS, check_whole_record

THERE = RECORDS[1::2]
pytestmark = pytest.mark.skipif(not RECORDS, reason="real BERT records not found (set GPNARX_BERT_DATA)")


@pytest.mark.parametrize("folder", THERE, ids=[p.name for p in THERE])
def test_whole_record_from_rest_does_not_diverge_and_is_covered(bert_real_model, folder):
    check_whole_record(bert_real_model, folder)
