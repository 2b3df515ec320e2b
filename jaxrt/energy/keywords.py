"""Keyword checks for the energy functions: a typo must raise, not vanish.

jax-md's displacement functions take ``**unused_kwargs``, so a misspelt
parameter (``sigmaa=2.``) handed on to them would be dropped without a
trace. The energy functions therefore accept only the keywords they or their
displacement function actually read, and name the rest.
"""
from __future__ import annotations

import difflib
import inspect
from typing import Callable, Iterable

# What jax_md.space displacement functions read from their **kwargs
# (``periodic_general``: box, new_box; all of them: perturbation).
SPACE_KEYWORDS = ("box", "new_box", "perturbation")
# Passed to the force function by jax_md.simulate's nvt_nose_hoover and
# npt_nose_hoover (they read kT= but leave it in **kwargs); an energy that
# rejected it would not be a drop-in there. Accepted and dropped.
SIMULATE_KEYWORDS = ("kT",)


def displacement_keywords(fn: Callable) -> tuple[str, ...]:
    """The keyword arguments ``fn(Ra, Rb, **kw)`` can use, as names.

    Named parameters after the two positions, plus `SPACE_KEYWORDS` when
    ``fn`` takes ``**kwargs`` (as every jax_md.space displacement does; a
    custom keyword of one's own must then be named in its signature).
    """
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):  # no signature to read: jax-md's set
        return SPACE_KEYWORDS
    names, positional, var_keyword = [], 0, False
    for p in params:
        if p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD):
            positional += 1
            if positional > 2 and p.kind is p.POSITIONAL_OR_KEYWORD:
                names.append(p.name)
        elif p.kind is p.KEYWORD_ONLY:
            names.append(p.name)
        elif p.kind is p.VAR_KEYWORD:
            var_keyword = True
    if var_keyword:
        names += [k for k in SPACE_KEYWORDS if k not in names]
    return tuple(names)


def reject_unknown(fn_name: str, given: Iterable[str],
                   own: Iterable[str], forwarded: Iterable[str] = (),
                   ignored: Iterable[str] = ()) -> None:
    """Raise ``TypeError`` naming every keyword in ``given`` that is not one
    of ``own`` (the function's parameters), ``forwarded`` (those handed to
    the displacement function) or ``ignored``, with "did you mean" hints."""
    own, forwarded, ignored = tuple(own), tuple(forwarded), tuple(ignored)
    accepted = own + tuple(k for k in forwarded + ignored if k not in own)
    unknown = sorted(set(given) - set(accepted))
    if not unknown:
        return
    hints = []
    for name in unknown:
        close = difflib.get_close_matches(name, accepted, n=1)
        if close:
            hints.append(f"{name!r}: did you mean {close[0]!r}?")
    accepts = ", ".join(own)
    if forwarded:
        accepts += (", and for the displacement function "
                    + ", ".join(forwarded))
    if ignored:
        accepts += ("; " + ", ".join(ignored) + " is also accepted and "
                    "ignored (jax_md.simulate passes it on)")
    raise TypeError(
        f"{fn_name}() got unexpected keyword argument(s) {unknown}"
        + (f" ({'; '.join(hints)})" if hints else "")
        + f"; it accepts {accepts}.")
