"""A digest of the program a function traces to, independent of what the process traced before.

`str(jax.make_jaxpr(fn)(...))` is not that: JAX's printer writes a sub-jaxpr once and refers to it by name
where the same *object* occurs twice, and whether two equal sub-jaxprs are one object depends on JAX's
trace caches, so on the tests that ran earlier in the same process (CI once saw the text of an unchanged
program differ). Here every sub-jaxpr is written out in full, with its variables numbered in order of
appearance; object identity only memoises the work.

Kept standalone (JAX only) so that it can digest an older checkout's programs too (test_precision.py).
"""

from __future__ import annotations

import hashlib
import re

import jax
import numpy as np
from jax.extend import core

ADDRESS = re.compile(r" at 0x[0-9a-fA-FX]+")  # object reprs in parameters (functions, treedef nodes)


def program_digest(fn, *args) -> str:
    """sha256 (first 16 hex digits) of the program `fn(*args)` traces to: primitives, parameters, shapes
    and dtypes, literals and the data flow. Like the printed jaxpr, it leaves out the values of closed-over
    arrays."""
    closed = jax.make_jaxpr(fn)(*args)
    return _jaxpr_hash(closed.jaxpr, {})[:16]


def _jaxpr_hash(jaxpr, memo: dict) -> str:
    if id(jaxpr) not in memo:
        names: dict = {}
        lines = ["in " + _vars(names, [*jaxpr.constvars, *jaxpr.invars])]
        lines += [_eqn_text(eqn, names, memo) for eqn in jaxpr.eqns]
        lines.append("out " + _vars(names, jaxpr.outvars))
        memo[id(jaxpr)] = hashlib.sha256("\n".join(lines).encode()).hexdigest()
    return memo[id(jaxpr)]


def _eqn_text(eqn, names: dict, memo: dict) -> str:
    params = " ".join(f"{key}={_param_text(value, memo)}" for key, value in sorted(eqn.params.items()))
    return f"{_vars(names, eqn.outvars)} = {eqn.primitive.name}[{params}] {_vars(names, eqn.invars)}"


def _vars(names: dict, variables) -> str:
    return " ".join(_var_text(names, v) for v in variables)


def _var_text(names: dict, v) -> str:
    if isinstance(v, core.Literal):
        return f"{v.val!r}:{v.aval.str_short()}"
    if isinstance(v, core.DropVar):
        return "_"
    if v not in names:
        names[v] = f"v{len(names)}:{v.aval.str_short()}"
    return names[v]


def _param_text(value, memo: dict) -> str:
    if isinstance(value, core.ClosedJaxpr):
        consts = ",".join(f"{np.result_type(c)}{np.shape(c)}" for c in value.consts)
        return f"closed({_jaxpr_hash(value.jaxpr, memo)};{consts})"
    if isinstance(value, core.Jaxpr):
        return f"jaxpr({_jaxpr_hash(value, memo)})"
    if isinstance(value, (tuple, list)):
        return "(" + ",".join(_param_text(v, memo) for v in value) + ")"
    return ADDRESS.sub(" at 0x", str(value))
