"""Integer words: ripple adders (1 AND per bit), negation, comparison, selection.

Ripple carry uses c' = c ^ ((x ^ c) & (y ^ c)), the one-AND full adder of free-XOR
garbling, so an n-bit add costs n AND gates (n-1 without the carry out). Comparators only
run the carry chain. Operands of different widths are zero-extended (``signed=False``)
or sign-extended to the wider width first.
"""

from __future__ import annotations

import numpy as np

from snail_common.circuit import ONE, ZERO, CircuitBuilder

from .words import Word, and_all, broadcast_lead, sext, wires, zext


def _extend(x: Word, bits: int, signed: bool) -> Word:
    return sext(x, bits) if signed else zext(x, bits)


def _align(x: Word, y: Word, signed: bool) -> tuple[Word, Word]:
    x, y = wires(x), wires(y)
    n = max(x.shape[-1], y.shape[-1])
    return tuple(broadcast_lead(_extend(x, n, signed), _extend(y, n, signed)))


def carries(b: CircuitBuilder, x: Word, y: Word, cin=ZERO, upto: int | None = None) -> Word:
    """Carries into bits 0..upto (default: n, i.e. including the carry out) of x + y + cin."""
    n = x.shape[-1]
    upto = n if upto is None else upto
    cin = wires(cin)
    lead = np.broadcast_shapes(x.shape[:-1], y.shape[:-1], cin.shape)
    x, y = (np.broadcast_to(w, lead + (n,)) for w in (x, y))
    c = np.broadcast_to(cin, lead).astype(np.int32)
    out = [c]
    for i in range(upto):
        c = b.xor(c, b.and_(b.xor(x[..., i], c), b.xor(y[..., i], c)))
        out.append(c)
    return np.stack(out, axis=-1)


def add(b: CircuitBuilder, x: Word, y: Word, cin=ZERO, signed: bool = False) -> Word:
    """x + y + cin modulo 2^n (n = wider operand): n-1 AND gates."""
    x, y = _align(x, y, signed)
    c = carries(b, x, y, cin, upto=x.shape[-1] - 1)
    return b.xor(b.xor(x, y), c)


def add_carry(b: CircuitBuilder, x: Word, y: Word, cin=ZERO,
              signed: bool = False) -> tuple[Word, np.ndarray]:
    """(x + y + cin mod 2^n, carry out): n AND gates."""
    x, y = _align(x, y, signed)
    c = carries(b, x, y, cin)
    return b.xor(b.xor(x, y), c[..., :-1]), c[..., -1]


def add_wide(b: CircuitBuilder, x: Word, y: Word, cin=ZERO, signed: bool = False) -> Word:
    """Exact x + y + cin as an (n+1)-bit word (unsigned: carry out; signed: sign-extended)."""
    x, y = wires(x), wires(y)
    n = max(x.shape[-1], y.shape[-1]) + 1
    return add(b, _extend(x, n, signed), _extend(y, n, signed), cin, signed)


def sub(b: CircuitBuilder, x: Word, y: Word, signed: bool = False) -> Word:
    """x - y modulo 2^n: n-1 AND gates."""
    x, y = _align(x, y, signed)
    return add(b, x, b.not_(y), ONE)


def sub_borrow(b: CircuitBuilder, x: Word, y: Word) -> tuple[Word, np.ndarray]:
    """(x - y mod 2^n, borrow = [x < y]) for unsigned words: n AND gates."""
    x, y = _align(x, y, False)
    s, c = add_carry(b, x, b.not_(y), ONE)
    return s, b.not_(c)


def add_sub(b: CircuitBuilder, x: Word, y: Word, subtract, signed: bool = False) -> Word:
    """x - y where ``subtract`` is 1, else x + y: the choice is free (XOR + carry in)."""
    x, y = _align(x, y, signed)
    s = np.asarray(subtract, np.int32)[..., None]
    return add(b, x, b.xor(y, s), subtract)


def increment(b: CircuitBuilder, x: Word, inc=ONE) -> tuple[Word, np.ndarray]:
    """(x + inc mod 2^n, carry out) for a 1-bit ``inc``: n AND gates (n-1 if carry unused
    and folded away)."""
    x = wires(x)
    c = np.broadcast_to(wires(inc), x.shape[:-1]).astype(np.int32)
    cs = []
    for i in range(x.shape[-1]):
        cs.append(c)
        c = b.and_(c, x[..., i])
    return b.xor(x, np.stack(cs, axis=-1)), c


def negate(b: CircuitBuilder, x: Word) -> Word:
    """-x modulo 2^n (two's complement): n-1 AND gates."""
    return cond_negate(b, x, ONE)


def cond_negate(b: CircuitBuilder, x: Word, neg) -> Word:
    """-x where ``neg`` is 1, else x (modulo 2^n): (x ^ neg) + neg, n-1 AND gates."""
    x = wires(x)
    n = np.asarray(neg, np.int32)
    y = b.xor(x, n[..., None])
    c = np.broadcast_to(n, y.shape[:-1]).astype(np.int32)
    cs = [c]
    for i in range(y.shape[-1] - 1):
        c = b.and_(c, y[..., i])
        cs.append(c)
    return b.xor(y, np.stack(cs, axis=-1))


def abs_signed(b: CircuitBuilder, x: Word) -> tuple[Word, np.ndarray]:
    """(|x| as an unsigned n-bit word, sign bit) of a two's complement word."""
    x = wires(x)
    s = x[..., -1]
    return cond_negate(b, x, s), s


def _msb_flip(b: CircuitBuilder, x: Word) -> Word:
    return np.concatenate([x[..., :-1], b.not_(x[..., -1:])], axis=-1)


def ge(b: CircuitBuilder, x: Word, y: Word, signed: bool = False) -> np.ndarray:
    """x >= y: the carry of x + ~y + 1, n AND gates."""
    x, y = _align(x, y, signed)
    if signed:
        x, y = _msb_flip(b, x), _msb_flip(b, y)
    return carries(b, x, b.not_(y), ONE)[..., -1]


def lt(b: CircuitBuilder, x: Word, y: Word, signed: bool = False) -> np.ndarray:
    """x < y: n AND gates."""
    return b.not_(ge(b, x, y, signed))


def le(b: CircuitBuilder, x: Word, y: Word, signed: bool = False) -> np.ndarray:
    """x <= y: n AND gates."""
    return ge(b, y, x, signed)


def gt(b: CircuitBuilder, x: Word, y: Word, signed: bool = False) -> np.ndarray:
    return lt(b, y, x, signed)


def eq(b: CircuitBuilder, x: Word, y: Word) -> np.ndarray:
    """x == y: n-1 AND gates (AND tree of XNORs)."""
    x, y = _align(x, y, False)
    return and_all(b, b.not_(b.xor(x, y)))


def select(b: CircuitBuilder, sel, if0: Word, if1: Word) -> Word:
    """Word-wide mux: one AND gate per bit that differs."""
    x, y = _align(if0, if1, False)
    return b.mux(np.asarray(sel, np.int32)[..., None], x, y)
