"""``ps-lab simulate`` with numbers and names it cannot use: one ``error:`` line, exit 2."""

from __future__ import annotations

from helpers.bad_input import NOT_UTF8, CaseTable, succeeded


CASES = CaseTable()
case = CASES.case
option_case = CASES.option_case


for _option, _value in (
    ("--max-zenith", "nan"),
    ("--max-zenith", "120"),
    ("--max-zenith", "-5"),
    ("--noise-sigma", "nan"),
    ("--roughness", "inf"),
    ("--specular", "nan"),
    ("--noise-fraction", "nan"),
    ("--size", "100000"),
):


    @case(f"g2-simulate{_option}-{_value}", (_option,))
    def _(w, option=_option, value=_value):
        return ["simulate", str(w.root / "new"), "--lights", "8", "--size", "16", option, value]


option_case("g5-simulate-unknown-scene", ["simulate"], "--scene", "cube", where="")
option_case("g5-simulate-unknown-format", ["simulate"], "--format", "jpg", where="")


@case("x-simulate-seed-negative", ("--seed",))
def _(w):
    return ["simulate", str(w.root / "new"), "--size", "16", "--lights", "8", "--seed", "-1"]


@case("x-simulate-into-dataset", lambda w: (str(w.ds),))
def _(w):
    return ["simulate", str(w.png()), "--size", "16", "--lights", "8"]


@case("x-simulate-two-lights", ("--lights",))
def _(w):
    return ["simulate", str(w.root / "new"), "--size", "16", "--lights", "2"]


@case("s3-simulate-not-utf8", (), code=0, check=succeeded)
def _(w):
    return ["simulate", str(w.root / NOT_UTF8), "--size", "16", "--lights", "8"]


#: The cases CI runs; ``pytest -m slow`` runs every case of the table.
CI_CASES = {
    "g2-simulate--max-zenith-nan",
    "g2-simulate--size-100000",
    "x-simulate-seed-negative",
}
test_bad_input = CASES.test(CI_CASES)
