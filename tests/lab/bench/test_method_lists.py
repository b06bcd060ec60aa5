"""Every ``agilegs bench`` command that takes selection methods runs any valid list in any
order and stops a wrong name with a one-line message naming it."""

from __future__ import annotations

import itertools

import pytest

from agilegs.config.selection import METHODS
from agilegs.lab.bench.variants import build_variants
from agilegs.service import cli


@pytest.mark.parametrize("argv, bad", [
    (["bench", "service", "--method", "oracle"], "--method: unknown method 'oracle'"),
    (["bench", "service", "--load-method", "agile@n20"], "--load-method: unknown method"),
    (["bench", "latency", "--methods", "random,oracle"], "oracle"),
    (["bench", "run", "--scene", "x", "--out", "y", "--methods", "agile,oracle"], "oracle"),
    (["bench", "proxy", "--scene", "x", "--driver", "oracle"], "oracle"),
])
def test_a_wrong_method_name_is_a_one_line_message(argv: list[str], bad: str,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    message = str(exc.value.code)
    assert bad in message and "\n" not in message.strip(), message


def test_every_order_of_the_methods_builds_the_same_variants() -> None:
    want = None
    for order in itertools.permutations(METHODS):
        got = sorted(v.key for v in build_variants(list(order), 10))
        assert want is None or got == want
        want = got
    assert want == sorted(METHODS)
