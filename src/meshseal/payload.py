"""The payload layer: a user's message <-> a model's N raw bits, keyed and protected by a BCH code.

Layout for a model of N raw bits (see docs/payload.md):

    data word (k bits, MSB first) = version (2) | kind (2) | payload (k - 4)
    codeword (N bits)             = BCH(2^m - 1, k) systematic codeword + 1 overall parity bit
    raw bits                      = (codeword XOR keystream) placed at keyed positions

    N = 64: BCH(63, 36), t = 5, extended distance 12 -> 32 payload bits
    N = 32: BCH(31, 16), t = 3, extended distance 8  -> 12 payload bits (legacy learned model)

The BCH code is galois's, imported on first use to encode, in pure-Python field arithmetic (its numba
JIT would cost every process a compile) and with the pinned polynomials taken as given, which skips their
verification; decoding runs on GF(2^m) log tables (`_bm_decode`), as galois decodes but without its
per-word cost. bchlib (C) only takes whole data bytes, so at t = 5 in GF(2^6) it would hold 32 data
bits instead of 36 and the 4-bit header would eat 4 payload bits. Timings: docs/payload.md.

The key (None = the public default key) derives, through SHAKE-256, the position permutation, the
keystream and `key_seed` for the model's own pattern: without the key the bits look random and a
message cannot be read. A decoded message means nothing on its own (random words decode to a valid
message now and then; docs/payload.md gives the rate): report it only when a p-value is at most `FPR`.
"""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import torch

from .errors import MeshsealError
# the schema and what a message may be live in `messages`, torch-free: the command line checks a message with them
from .messages import KINDS, SCHEMA_VERSION, SCHEMAS, Message, payload_bits
from .messages import Schema as _Schema, payload_value as _payload_value, schema as _schema

FPR = 1e-6
DEFAULT_KEY = b"meshseal public key"


# The distributions' tails, from torch in float64 (imported already; scipy.special would add a tenth of
# a second to every command's start): the lower normal tail through erfc (accurate far into the tail,
# where torch's own ndtr loses its relative precision), erfcx as scipy's (both the Faddeeva package's),
# chi-square and Poisson through the regularised incomplete gamma functions.


def _float64(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def _as_input(x, value: torch.Tensor):
    """value shaped as x was given: a float for a scalar, an array for an array."""
    return float(value) if np.ndim(x) == 0 else value.numpy()


def _normal_below(x):
    """P(N(0, 1) <= x) (scipy's `ndtr`)."""
    value = _float64(x)
    low = 0.5 * torch.erfc(-value / math.sqrt(2.0))
    return _as_input(x, torch.where(value < 0, low, 1.0 - 0.5 * torch.erfc(value / math.sqrt(2.0))))


def _erfcx(x):
    """exp(x^2) erfc(x) (scipy's `erfcx`)."""
    return _as_input(x, torch.special.erfcx(_float64(x)))


def _chi_square_above(k: int, x):
    """P(chi-square(k) >= x) (scipy's `chdtrc`)."""
    value = _float64(x)
    return _as_input(x, torch.special.gammaincc(torch.full_like(value, k / 2.0), value / 2.0))


def _poisson_above(k: int, mean: float) -> float:
    """P(Poisson(mean) > k) for k >= 0 (scipy's `pdtrc`)."""
    return float(torch.special.gammainc(_float64(k + 1.0), _float64(mean)))


@lru_cache(maxsize=None)
def _code(n_bits: int):
    """The galois BCH code of a schema, built once (the field polynomial is pinned: it fixes the code)."""
    import galois

    schema = _schema(n_bits)
    # GF(2) first, in pure Python: built by default, it JIT-compiles a polynomial evaluation.
    galois.GF(2, compile="python-calculate")
    field = galois.GF(2 ** schema.m, irreducible_poly=schema.primitive_poly, compile="python-calculate", verify=False)
    code = galois.BCH(2 ** schema.m - 1, d=schema.d, extension_field=field)
    if code.k != schema.k:  # pragma: no cover - the schema table is wrong
        raise MeshsealError(f"BCH(2^{schema.m} - 1, d={schema.d}) has k = {code.k}, the schema says {schema.k}")
    return code


@dataclass(frozen=True)
class Decoded:
    """What `decode` read. message: str (text), int (id), '0101...' (raw) or None when the codeword
    failed or did not hold a valid message; errors_corrected: raw bits flipped to reach the codeword
    (None when it failed); bits: the raw hard bits, '1' where the soft value is > 0."""

    message: str | int | None
    kind: str | None
    version: int | None
    errors_corrected: int | None
    codeword_ok: bool
    bits: str


# --- keys -------------------------------------------------------------------------------------------

def _key_bytes(key: str | bytes | None) -> bytes:
    if key is None:
        return DEFAULT_KEY
    if isinstance(key, str):
        key = key.encode("utf-8")
    if not isinstance(key, (bytes, bytearray)):
        raise MeshsealError(f"key must be text or bytes, got {type(key).__name__}")
    if not key:
        raise MeshsealError("key is empty; leave it out to use the public default key")
    return bytes(key)


def _derive(key: str | bytes | None, purpose: str, n_bytes: int) -> bytes:
    """SHAKE-256("meshseal/v1/" + purpose + NUL + key): purposes never contain NUL, so no two
    (purpose, key) pairs share an input."""
    return hashlib.shake_256(b"meshseal/v1/" + purpose.encode() + b"\0" + _key_bytes(key)).digest(n_bytes)


def key_seed(key: str | bytes | None = None) -> int:
    """A 63-bit seed for the model's mark pattern, so that the mark itself depends on the key."""
    return int.from_bytes(_derive(key, "pattern", 8), "big") >> 1


def _permutation(key, n_bits: int) -> np.ndarray:
    """Raw position of each codeword bit: the ranks of N derived 64-bit integers."""
    values = np.frombuffer(_derive(key, f"permutation/{n_bits}", 8 * n_bits), dtype=">u8")
    return np.argsort(values, kind="stable")


def _keystream(key, n_bits: int) -> np.ndarray:
    return np.unpackbits(np.frombuffer(_derive(key, f"keystream/{n_bits}", (n_bits + 7) // 8), np.uint8))[:n_bits]


# --- encode -----------------------------------------------------------------------------------------

def encode(message: str | int | Message, key: str | bytes | None = None, n_bits: int = 64) -> torch.Tensor:
    """Raw bits (n_bits,) of 0./1. carrying `message` (str: text, int: ID, or a Message) under `key`."""
    schema = _schema(n_bits)
    kind, value = _payload_value(message, n_bits)
    word = (SCHEMA_VERSION << (schema.k - 2)) | (kind << schema.payload_bits) | value
    data = np.array([(word >> (schema.k - 1 - i)) & 1 for i in range(schema.k)], dtype=np.uint8)
    codeword = np.asarray(_code(n_bits).encode(data), dtype=np.uint8)
    codeword = np.append(codeword, np.uint8(codeword.sum() % 2)) ^ _keystream(key, n_bits)
    raw = np.empty(n_bits, dtype=np.uint8)
    raw[_permutation(key, n_bits)] = codeword
    return torch.from_numpy(raw.astype(np.float32))


def encode_many(messages, key: str | bytes | None = None, n_bits: int = 64) -> torch.Tensor:
    """Raw bits (M, n_bits) of 0./1. for many messages at once (an owner's list of asset IDs, say):
    row i is `encode(messages[i], key, n_bits)`. The code, the parity bit, the whitening and the
    placement are all linear over GF(2) (the whitening affine), so each row is the zero word's raw bits
    XOR the data bits times a k x n_bits matrix built once from the generator polynomial, without
    galois and in one matrix product. The last list's answer is kept (a picture's decision asks for it
    several times)."""
    messages = tuple(messages)
    if _LAST_MANY and _LAST_MANY[0] == (key, n_bits, messages):
        return _LAST_MANY[1]
    schema = _schema(n_bits)
    words = []
    for message in messages:
        kind, value = _payload_value(message, n_bits)
        words.append((SCHEMA_VERSION << (schema.k - 2)) | (kind << schema.payload_bits) | value)
    shifts = np.arange(schema.k - 1, -1, -1, dtype=np.uint64)
    data = ((np.asarray(words, dtype=np.uint64)[:, None] >> shifts) & np.uint64(1)).astype(np.int64)  # (M, k)
    rows = _generator_rows(n_bits, key)  # (k, n_bits): the raw bits each data bit flips
    raw = (data @ rows) % 2 ^ _raw_of_zero(n_bits, key)
    result = torch.from_numpy(raw.astype(np.float32))
    _LAST_MANY[:] = [(key, n_bits, messages), result]
    return result


_LAST_MANY: list = []


def _codeword_bits(word: int, n_bits: int) -> np.ndarray:
    """The systematic BCH codeword of data word `word` (data first, then the check bits: the remainder
    of data(x) x^(n-k) by the generator) and the overall parity bit: (n_bits,) uint8."""
    schema, generator = _schema(n_bits), GENERATORS[n_bits]
    checks = generator.bit_length() - 1
    remainder = word << checks
    while remainder.bit_length() > checks:
        remainder ^= generator << (remainder.bit_length() - 1 - checks)
    value = (word << checks) | remainder
    bits = np.array([(value >> (n_bits - 2 - i)) & 1 for i in range(n_bits - 1)], dtype=np.uint8)
    assert schema.k + checks == n_bits - 1
    return np.append(bits, np.uint8(bits.sum() % 2))


def _placed(codeword: np.ndarray, key, n_bits: int, whiten: bool) -> np.ndarray:
    raw = np.empty(n_bits, dtype=np.uint8)
    raw[_permutation(key, n_bits)] = codeword ^ _keystream(key, n_bits) if whiten else codeword
    return raw


def _raw_of_zero(n_bits: int, key) -> np.ndarray:
    return _placed(np.zeros(n_bits, dtype=np.uint8), key, n_bits, True).astype(np.int64)


def _generator_rows(n_bits: int, key) -> np.ndarray:
    schema = _schema(n_bits)
    return np.stack([_placed(_codeword_bits(1 << (schema.k - 1 - i), n_bits), key, n_bits, False)
                     for i in range(schema.k)]).astype(np.int64)


# --- decode -----------------------------------------------------------------------------------------

def _as_soft(soft) -> np.ndarray:
    if isinstance(soft, torch.Tensor):
        soft = soft.detach().cpu().double().numpy()
    values = np.asarray(soft, dtype=np.float64)
    if not np.isfinite(values).all():
        raise MeshsealError("soft bits must be finite numbers")
    return values


# Each schema's BCH generator polynomial g(x) (bit i: the coefficient of x^i) and its correctable errors
# t = (d - 1) // 2: galois' `_code(n).generator_poly` and `.t` (tests/test_payload.py checks them), kept
# here so that a word that is already a codeword is recognised without importing galois.
GENERATORS = {64: 0x86E8113, 32: 0x8FAF}


def _is_codeword(word: np.ndarray) -> bool:
    """Whether BCH bits `word` (n,), highest degree first as galois orders them, are a codeword:
    g(x) divides the word's polynomial (no syndrome; most pictures with a mark read one, and galois'
    decoder takes milliseconds to say so)."""
    generator = GENERATORS[len(word) + 1]
    remainder, degree = int("".join("1" if bit else "0" for bit in word), 2), generator.bit_length() - 1
    while remainder.bit_length() > degree:
        remainder ^= generator << (remainder.bit_length() - 1 - degree)
    return remainder == 0


@lru_cache(maxsize=None)
def _field_tables(m: int, primitive_poly: str) -> tuple[list[int], list[int]]:
    """Antilog (twice over, so sums of two logs need no reduction) and log tables of GF(2^m) built on
    `primitive_poly` ("x^6 + x + 1"): alpha^i and log_alpha(a)."""
    poly = sum(1 << (int(term[2:]) if term.startswith("x^") else 1 if term == "x" else 0)
               for term in primitive_poly.replace(" ", "").split("+"))
    size = (1 << m) - 1
    antilog, log = [0] * (2 * size), [0] * (size + 1)
    value = 1
    for power in range(size):
        antilog[power] = antilog[power + size] = value
        log[value] = power
        value <<= 1
        if value >> m:
            value ^= poly
    return antilog, log


def _bm_decode(word: np.ndarray, schema: _Schema) -> tuple[np.ndarray, int]:
    """The narrow-sense BCH(2^m - 1, k) codeword nearest to hard bits `word` (n,) (highest degree first,
    as galois orders them) and the number of bits it corrected, or (word, -1) where more than t errors
    are seen: syndromes, Berlekamp-Massey, Chien search, on log tables. galois' decoder gives the same
    answers (tests/test_payload.py checks it on random words) but in pure-Python field arithmetic takes
    milliseconds a word, as long as a whole camera-known reading's texture stage."""
    antilog, log = _field_tables(schema.m, schema.primitive_poly)
    size, t = (1 << schema.m) - 1, (schema.d - 1) // 2
    degrees = [size - 1 - index for index in np.flatnonzero(word)]
    syndromes = []
    for j in range(1, 2 * t + 1):
        value = 0
        for degree in degrees:
            value ^= antilog[(j * degree) % size]
        syndromes.append(value)
    if not any(syndromes):
        return word.astype(np.uint8), 0
    multiply = lambda a, b: 0 if a == 0 or b == 0 else antilog[log[a] + log[b]]  # noqa: E731
    locator, previous, length, shift, last = [1], [1], 0, 1, 1  # Berlekamp-Massey
    for step in range(2 * t):
        discrepancy = syndromes[step]
        for i in range(1, length + 1):
            if i < len(locator):
                discrepancy ^= multiply(locator[i], syndromes[step - i])
        if discrepancy == 0:
            shift += 1
            continue
        factor = antilog[(log[discrepancy] - log[last]) % size]
        update = locator + [0] * max(0, len(previous) + shift - len(locator))
        for i, coefficient in enumerate(previous):
            update[i + shift] ^= multiply(factor, coefficient)
        if 2 * length <= step:
            previous, length, last, shift = locator, step + 1 - length, discrepancy, 1
        else:
            shift += 1
        locator = update
    while len(locator) > 1 and locator[-1] == 0:
        locator.pop()
    if length > t or len(locator) - 1 != length:
        return word.astype(np.uint8), -1
    errors = []  # Chien search: an error at degree e where the locator vanishes at alpha^-e
    for degree in range(size):
        value = 0
        for i, coefficient in enumerate(locator):
            if coefficient:
                value ^= antilog[(log[coefficient] - i * degree) % size]
        if value == 0:
            errors.append(degree)
    if len(errors) != length:
        return word.astype(np.uint8), -1
    decoded = word.astype(np.uint8).copy()
    decoded[[size - 1 - degree for degree in errors]] ^= 1
    return decoded, length


def _bch_decode(word: np.ndarray) -> np.ndarray | None:
    """The extended-code codeword (N,) nearest to hard bits `word` (N,), or None. A word is accepted
    when the BCH errors plus a mismatched overall parity bit are at most t, so the extended code's
    t + 1 errors are always detected rather than miscorrected."""
    if _is_codeword(word[:-1]):
        decoded, n_errors = word[:-1].astype(np.uint8), 0  # a codeword already: the decoder's own answer, at no cost
    else:
        decoded, n_errors = _bm_decode(word[:-1], _schema(len(word)))
    parity = np.uint8(decoded.sum() % 2)
    if n_errors < 0 or n_errors + (parity != word[-1]) > (_schema(len(word)).d - 1) // 2:
        return None
    return np.append(decoded, parity)


def _message(word: int, schema: _Schema) -> tuple[str | int | None, str | None, int]:
    """(message, kind, version) of a data word; message None when it is not a valid message."""
    size = schema.payload_bits
    version, kind, value = word >> (size + 2), (word >> size) & 3, word & (2 ** size - 1)
    if version != SCHEMA_VERSION or kind >= len(KINDS):
        return None, None, version
    name = KINDS[kind]
    if name == "id":
        return value, name, version
    if name == "raw":
        return format(value, f"0{size}b"), name, version
    limit = size // 8
    if value >> (8 * limit):
        return None, name, version
    data = value.to_bytes(limit, "big").rstrip(b"\0")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        return None, name, version
    return (None if "\0" in text else text), name, version


def decode(soft, key: str | bytes | None = None, soft_retry: bool = True) -> Decoded:
    """Read the message from soft bits (N,) under `key`: the signs, hard-decoded (bit '1' where > 0);
    where that fails, the most likely codeword given the soft values (`_soft_decode`), taken only where
    it is far likelier than every other codeword near it. A wrong message is worse than none: the
    retry accepts a codeword only at a posterior of 1 - SOFT_RISK or more, and a hard decoding that
    corrected VERIFY_FROM bits or more is kept only at a posterior of 1 - VERIFY_RISK or more (hard
    decoding's miscorrections; docs/payload.md, "Soft decoding"). `soft_retry` False: the hard
    decoding alone, unchecked (for soft values that are not z-scores)."""
    z = _as_soft(soft)
    if z.ndim != 1:
        raise MeshsealError(f"soft bits must be one vector, got shape {tuple(z.shape)}")
    schema, n_bits = _schema(len(z)), len(z)
    bits = "".join("1" if v > 0 else "0" for v in z)
    permutation, keystream = _permutation(key, n_bits), _keystream(key, n_bits)
    hard = (z[permutation] > 0).astype(np.uint8) ^ keystream
    codeword = _bch_decode(hard)
    if codeword is not None and soft_retry and int((codeword != hard).sum()) >= VERIFY_FROM:
        # Several bits corrected: a codeword within t of the signs need not be the likely one (hard
        # decoding miscorrects there); kept only where the soft values make it clearly the likeliest.
        if _posterior(z, key, _placed(codeword, key, n_bits, True)) < 1.0 - VERIFY_RISK:
            return Decoded(None, None, None, None, False, bits)
    if codeword is None and soft_retry:  # no codeword within t of the signs: the likeliest, where it is clearly so
        raw = _soft_decode(z, key)
        if raw is not None:
            codeword = raw[permutation] ^ keystream
    if codeword is None:
        return Decoded(None, None, None, None, False, bits)
    message, kind, version = _message(int("".join(map(str, codeword[:schema.k])), 2), schema)
    return Decoded(message, kind, version, int((codeword != hard).sum()), True, bits)


VERIFY_FROM = 3  # a hard decoding that corrected this many bits or more is checked against the soft values ...
VERIFY_RISK = 0.1  # ... and kept only where its posterior among the soft decoding's candidates is at least 1 - this
SOFT_ORDER = 2  # the soft decoding's candidates: the most reliable information set's hard bits with up to this many flipped
SOFT_RISK = 1e-2  # ... and a codeword is taken only where its posterior among them is at least 1 - this


@lru_cache(maxsize=8)
def _code_layout(key_bytes: bytes, n_bits: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The code in raw bit positions under a key: generator rows (k, N), the whitening (N,) (a raw
    codeword is data @ rows + whitening, mod 2) and the soft decoding's flip patterns (L, k)."""
    rows = _generator_rows(n_bits, key_bytes).astype(np.uint8)
    k = rows.shape[0]
    flips = [()] + [combination for order in range(1, SOFT_ORDER + 1)
                    for combination in itertools.combinations(range(k), order)]
    patterns = np.zeros((len(flips), k), dtype=np.uint8)
    for index, flipped in enumerate(flips):
        patterns[index, list(flipped)] = 1
    return rows, _raw_of_zero(n_bits, key_bytes).astype(np.uint8), patterns


def _soft_decode(z: np.ndarray, key) -> np.ndarray | None:
    """The raw bits (N,) of the codeword most likely given soft bits `z` (N,), or None where it is not
    clearly the most likely. Ordered-statistics decoding (Fossorier and Lin, 1995): the k most reliable
    positions that determine a codeword (Gaussian elimination over GF(2) in order of |z|), their hard
    bits with up to SOFT_ORDER of them flipped, each re-encoded; the best-correlated codeword wins.
    Soft bits are modelled as mu * (+-1) + N(0, 1), mu estimated from the winner's own correlation;
    the winner's posterior among the candidates, 1 / sum_c exp(-mu (corr_best - corr_c)), must be at
    least 1 - SOFT_RISK. The candidates include the codewords nearest the winner, so a word about as
    likely as another is refused. Run only where hard decoding found no codeword within t."""
    ordered, order, candidates, correlation, whitening = _candidates(z, key)
    if candidates is None:
        return None
    best = int(correlation.argmax())
    mu = correlation[best] / len(z)
    if not mu > 0:
        return None
    posterior = 1.0 / np.exp(-mu * (correlation[best] - correlation)).sum()
    if posterior < 1.0 - SOFT_RISK:
        return None
    # The soft values must explain the winner's disagreements with the hard bits: under the model each
    # hard bit is wrong with probability 1 / (1 + exp(2 mu |z|)), so the disagreements should number
    # about the sum of those. Far more (a Poisson tail under SOFT_RISK) means the magnitudes do not say
    # which bits are wrong (e.g. all equal), and then a list that misses the true codeword can name
    # another with a posterior that only looks high.
    disagree = int(((candidates[best] == 1) != (ordered > 0)).sum())
    expected = float((1.0 / (1.0 + np.exp(np.minimum(2.0 * mu * np.abs(ordered), 700.0)))).sum())
    if disagree > 0 and _poisson_above(disagree - 1, expected) < SOFT_RISK:
        return None
    raw = np.empty(len(z), dtype=np.uint8)
    raw[order] = candidates[best].astype(np.uint8)
    return raw ^ whitening


def _posterior(z: np.ndarray, key, raw: np.ndarray) -> float:
    """The posterior of the codeword with raw bits `raw` (N,) among itself and the soft decoding's
    candidates (the model of `_soft_decode`, mu from the best-correlated of them); 0 where the soft
    values do not favour any."""
    ordered, order, candidates, correlation, whitening = _candidates(z, key)
    if candidates is None:
        return 0.0
    own = (raw ^ whitening)[order].astype(np.int64)
    own_correlation = float(((2.0 * own - 1.0) * ordered).sum())
    others = correlation[~(candidates == own).all(1)]
    mu = max(own_correlation, float(others.max(initial=-np.inf))) / len(z)
    if not mu > 0:
        return 0.0
    return float(1.0 / (1.0 + np.exp(-mu * (own_correlation - others)).sum()))


def _candidates(z: np.ndarray, key):
    """The ordered-statistics decoder's candidate codewords for soft bits `z` (N,): the soft values of
    the unwhitened code's bits in order of reliability (N,), that order (N,), the candidates in that
    order (L, N), their correlations with the soft values (L,) and the key's whitening (N,); None
    candidates where the bits do not determine a codeword (never, for a code's own generator rows)."""
    n_bits = len(z)
    rows, whitening, patterns = _code_layout(_key_bytes(key), n_bits)
    k = rows.shape[0]
    signed = np.where(whitening == 1, -z, z)  # soft values of the unwhitened (linear) code's bits
    order = np.argsort(-np.abs(signed), kind="stable")
    matrix = rows[:, order].copy()
    pivots, row = [], 0
    for column in range(n_bits):
        if row == k:
            break
        below = np.flatnonzero(matrix[row:, column])
        if len(below) == 0:
            continue  # dependent on the more reliable columns already taken
        if below[0]:
            matrix[[row, row + below[0]]] = matrix[[row + below[0], row]]
        others = np.flatnonzero(matrix[:, column])
        others = others[others != row]
        matrix[others] ^= matrix[row]
        pivots.append(column)
        row += 1
    ordered = signed[order]
    if row < k:
        return ordered, order, None, None, whitening
    information = (ordered[pivots] > 0).astype(np.uint8)
    # Distinct information bits give distinct codewords: no candidate repeats another.
    candidates = ((information[None] ^ patterns).astype(np.int64) @ matrix.astype(np.int64)) % 2  # (L, N)
    return ordered, order, candidates, ((2.0 * candidates - 1.0) * ordered).sum(1), whitening


# --- p-values under the null model: no mark under this key ---------------------------------------------

def detection_pvalue(z, weights=None) -> float | np.ndarray:
    """P(T >= t | H0) for T = sum_i z_i^2: any mark under this key, whatever message.

    weights (N, M) per picture (`models.spread.bit_weights`: each bit's cell evidence): the exact null
    given the picture, z_b a Rademacher sum with these weights (see above). None: z iid N(0, 1),
    T ~ chi-square(N) (models without cell evidence). z (N,) gives a float, z (..., N) with weights
    (..., N, M) an array; floored at the smallest normal float, never 0."""
    values = _as_soft(z)
    statistic = (values ** 2).sum(-1)
    if weights is None:
        p = _chi_square_above(values.shape[-1], statistic)
    else:
        weights = _as_soft(weights)
        if weights.shape[:-1] != values.shape:
            raise MeshsealError(f"weights of shape {weights.shape} do not fit soft bits of shape {values.shape}")
        p = np.array([_exact_square_sum_pvalue(t, w) for t, w in
                      zip(statistic.ravel(), weights.reshape(-1, *weights.shape[-2:]))]).reshape(statistic.shape)
    p = np.maximum(p, np.finfo(float).tiny)
    return float(p) if p.ndim == 0 else p


PILOT_SHARE = 0.9  # the pilot's part of the false-positive rate where a mark has one; the bits' test has the rest


def any_mark_pvalue(bits_p: float, pilot_p: float | None, share: float = PILOT_SHARE) -> float:
    """The p-value of "a mark under this key, whatever message" from the bits' test and, where the
    mark has one, the pilot's: weighted Bonferroni, min(pilot / s, bits / (1 - s)) for s = PILOT_SHARE,
    exact or conservative whatever the two tests' dependence (P(p_pilot <= s a) + P(p_bits <= (1 - s) a)
    <= a). The pilot gets the larger part: it is the stronger test of the two on pictures, the bits'
    test finding a mark the pilot misses almost never. `share` 0 or 1 leaves one test alone."""
    if pilot_p is None:
        return min(1.0, bits_p)
    parts = ([pilot_p / share] if share > 0 else []) + ([bits_p / (1.0 - share)] if share < 1 else [])
    return min(1.0, *parts)


def match_pvalue(z, expected_bits, weights=None) -> float | np.ndarray:
    """P(S >= s | H0) for S = sum_i z_i (2 b_i - 1) / sqrt(N), b the expected raw bits (`encode`'s
    output or '0101...'): the picture carries this very message. With `weights` S is a Rademacher
    sum (the exact null given the picture), without them N(0, 1). Same shapes and floor as
    `detection_pvalue`."""
    values = _as_soft(z)
    if isinstance(expected_bits, str):
        if set(expected_bits) - {"0", "1"}:
            raise MeshsealError("expected bits must be a string of 0 and 1")
        expected_bits = [int(bit) for bit in expected_bits]
    expected = _as_soft(expected_bits)
    if not np.isin(expected, (0.0, 1.0)).all():
        raise MeshsealError("expected bits must be 0 or 1")
    if expected.shape != values.shape[-1:]:
        raise MeshsealError(f"expected {expected.size} bits, but the model reads {values.shape[-1]}")
    statistic = (values * (2.0 * expected - 1.0)).sum(-1) / math.sqrt(values.shape[-1])
    if weights is None:
        p = _normal_below(-statistic)
    else:
        weights = _as_soft(weights)
        if weights.shape[:-1] != values.shape:
            raise MeshsealError(f"weights of shape {weights.shape} do not fit soft bits of shape {values.shape}")
        energy = np.sqrt((weights ** 2).sum(-1, keepdims=True))
        unit = weights / np.where(energy > 0, energy, 1.0) / math.sqrt(values.shape[-1])
        p = np.array([_exact_sum_pvalue(s, w) for s, w in
                      zip(statistic.ravel(), unit.reshape(-1, *unit.shape[-2:]))]).reshape(statistic.shape)
    p = np.maximum(p, np.finfo(float).tiny)
    return float(p) if p.ndim == 0 else p



# --- the exact null: z_b = sum_i w_bi s_i, the key's random cell signs s_i, weights from the picture ----
#
# The spread-spectrum detector's z_b is a normalised sum of cell evidence times the key's random signs
# (`models.spread.soft_bits`). Without a mark under this key the signs are independent of the picture,
# so given the picture each z_b is a Rademacher sum with known weights w_bi (`models.spread.bit_weights`):
# bounded, with lighter tails than N(0, 1) whenever a few cells carry most of a bit's evidence. The
# p-values below are that distribution's tail, by a saddlepoint approximation (Lugannani-Rice, relative
# error O(1/cells)) instead of the chi-square / normal tail of the N(0, 1) model, which over-states them.

def _half_rule(points: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite nodes h > 0 and weights for E_g f(g), g ~ N(0, 1), f even (the integrands here)."""
    nodes, weights = np.polynomial.hermite_e.hermegauss(points)
    keep = (nodes > 0) & (weights > 1e-15 * math.sqrt(2.0 * math.pi))
    return nodes[keep], 2.0 * weights[keep] / math.sqrt(2.0 * math.pi)


# Bits of FEW_CELLS effective cells or more (so no cell weighs over 8^-1/4 = 0.59) are smooth in h:
# 16 points give p within 1e-4 of 48 points while no cell weighs more than 0.7.
_RULE = _half_rule(16)
FEW_CELLS = 8


def _log_cosh_root(y: np.ndarray, positive: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """psi(y) = log cosh(sqrt y) - y / 2 for y >= 0 (`positive`), continued to y <= 0 as
    log cos sqrt(-y) + |y| / 2: log |e^psi|, where e^psi < 0, psi' and psi''. A series near 0, where
    the closed forms cancel."""
    log_abs = y * y * (-1 / 12 + y * (1 / 45 - y * 17 / 2520))
    first = y * (-1 / 6 + y * (1 / 15 - y * 17 / 630))
    second = -1 / 6 + y * (2 / 15 - y * 17 / 210)
    negative = np.zeros(y.shape, dtype=bool)
    large = np.abs(y) >= 1e-2
    x = y[large]
    root = np.sqrt(np.abs(x))
    if positive:
        decay = np.exp(-2.0 * root)
        tanh = (1.0 - decay) / (1.0 + decay)
        log_abs[large] = root + np.log1p(decay) - math.log(2.0) - x / 2
        first[large] = tanh / (2.0 * root) - 0.5
        second[large] = (root * (1.0 - tanh * tanh) - tanh) / (4.0 * root ** 3)
    else:
        cos = np.cos(root)
        tan = np.sin(root) / cos
        log_abs[large] = np.log(np.maximum(np.abs(cos), 1e-300)) - x / 2
        first[large] = tan / (2.0 * root) - 0.5
        second[large] = -(root / np.maximum(cos * cos, 1e-300) - tan) / (4.0 * root ** 3)
        negative[large] = cos < 0
    return log_abs, negative, first, second


def _square_sum_cgf(lam: float, n: int, groups) -> tuple[float, float, float]:
    """K, K', K'' at lam < 1/2 of T = sum_b z_b^2 over n bits, z_b = sum_i w_bi s_i; bits in none of
    `groups` count as chi-square(1) (`_exact_square_sum_pvalue`'s few-cell bits). Each of `groups` is (node
    weights (Q,), scaled (Q, P): h_q^2 w_i^2 for the nodes h_q and every cell i with weight, the cells of
    a bit contiguous from `starts`); each bit's w^2 sum to 1. Gaussian trick: E exp(lam z^2) =
    E_g prod_i cosh(sqrt(2 lam) g w_i); with g = h / sqrt(1 - 2 lam) it is (1 - 2 lam)^-1/2
    E_h exp(sum_i psi(h^2 w_i^2 u)), u = 2 lam / (1 - 2 lam)."""
    u = 2.0 * lam / (1.0 - 2.0 * lam)
    du, ddu = 2.0 / (1.0 - 2.0 * lam) ** 2, 8.0 / (1.0 - 2.0 * lam) ** 3
    log_total, l1_sum, l2_sum = 0.0, 0.0, 0.0
    for node_weights, scaled, starts in groups:
        log_abs, negative, first, second = _log_cosh_root(scaled * u, u >= 0)
        bits = lambda values: np.add.reduceat(values, starts, axis=1)  # noqa: E731  (Q, bits)
        log_f = bits(log_abs)
        sign = 1.0 - 2.0 * (bits(negative.astype(np.float64)) % 2)
        a = bits(scaled * first)  # d log f / du
        b = bits(scaled * scaled * second)
        top = log_f.max(0)
        f = node_weights[:, None] * sign * np.exp(log_f - top)
        total = f.sum(0)
        l1 = (f * a).sum(0) / total
        log_total += float((np.log(total) + top).sum())
        l1_sum += float(l1.sum())
        l2_sum += float(((f * (a * a + b)).sum(0) / total - l1 * l1).sum())
    k = -0.5 * n * math.log1p(-2.0 * lam) + log_total
    k1 = n / (1.0 - 2.0 * lam) + l1_sum * du
    k2 = 2.0 * n / (1.0 - 2.0 * lam) ** 2 + l2_sum * du * du + l1_sum * ddu
    return k, k1, k2


def _rademacher_cgf(lam: float, weights: np.ndarray) -> tuple[float, float, float]:
    """K, K', K'' of S = sum_i v_i s_i: K = sum log cosh(lam v)."""
    x = lam * weights
    ax = np.abs(x)
    tanh = np.tanh(x)
    return (float((ax + np.log1p(np.exp(-2.0 * ax)) - math.log(2.0)).sum()), float((weights * tanh).sum()),
            float((weights * weights * (1.0 - tanh * tanh)).sum()))


def _saddlepoint_tail(t: float, cgf, lower: float, upper: float, mean: float, variance: float,
                      start: float | None = None) -> float:
    """P(X >= t) by Lugannani-Rice from X's cumulant generating function `cgf(lam) -> (K, K', K'')`,
    defined on (lower, upper), Newton's method from `start` (default: the normal's saddlepoint); the
    normal tail (exact mean and variance) where the saddlepoint is 0."""
    lam = float(np.clip((t - mean) / variance if start is None else start, lower, upper))
    low, high = lower, upper
    for _ in range(100):
        k, k1, k2 = cgf(lam)
        if k1 > t:
            high = lam
        else:
            low = lam
        if abs(k1 - t) <= 1e-10 * max(1.0, abs(t)):
            break
        if (lam >= upper and k1 < t) or (lam <= lower and k1 > t):
            break  # t beyond what the range reaches
        step = lam - (k1 - t) / k2
        if low < step < high:
            lam = step
        elif step >= high == upper or step <= low == lower:
            lam = upper if step >= high else lower  # try the end of the range once
        else:
            lam = 0.5 * (low + high)
    if (k1 < t and lam >= upper) or (k1 > t and lam <= lower):  # t beyond the range: Chernoff bound
        bound = math.exp(min(k - lam * t, 0.0))
        return max(bound, np.finfo(float).tiny) if k1 < t else 1.0 - bound
    w_hat = math.copysign(math.sqrt(max(2.0 * (lam * t - k), 0.0)), lam)
    if abs(w_hat) < 1e-2:
        return float(_normal_below(-(t - mean) / math.sqrt(variance)))
    u_hat = lam * math.sqrt(k2)
    chernoff = math.exp(-0.5 * w_hat ** 2)  # exp(K - lam t): P(X >= t) <= this above the mean, P(X < t) below
    if w_hat < 5.0:
        p = float(_normal_below(-w_hat) + math.exp(-0.5 * w_hat ** 2) / math.sqrt(2 * math.pi) * (1 / u_hat - 1 / w_hat))
    else:
        mills = math.sqrt(math.pi / 2) * _erfcx(w_hat / math.sqrt(2))  # P(N > w) / phi(w)
        p = math.exp(-0.5 * w_hat ** 2 - 0.5 * math.log(2 * math.pi)) * (mills + 1 / u_hat - 1 / w_hat)
    # The approximation can leave [0, 1] where X is nearly discrete; the Chernoff bounds always hold.
    return min(max(p, 0.0), chernoff) if lam > 0 else max(min(p, 1.0), 1.0 - chernoff)


def _exact_square_sum_pvalue(t: float, weights: np.ndarray) -> float:
    """P(T >= t) for T = sum_b z_b^2 given each bit's cell weights (N, M) (any scale; zero rows: bits
    the picture does not show, z_b = 0). A bit with fewer than FEW_CELLS effective cells (1 / sum w^4)
    takes part as chi-square(1): its z^2 is nearly discrete (one cell: z^2 = 1), where a saddlepoint
    misleads, and chi-square(1) has the larger moment generating function, hence the safer tail."""
    squares = np.asarray(weights, dtype=np.float64) ** 2
    energy = squares.sum(-1)
    squares = squares[energy > 0] / energy[energy > 0, None]
    if not len(squares):
        return 1.0
    n = len(squares)
    smooth = (squares ** 2).sum(-1) < 1.0 / FEW_CELLS
    variance = 2.0 * n - 2.0 * float((squares[smooth] ** 2).sum())
    groups = []
    if smooth.any():
        nodes, node_weights = _RULE
        rows = squares[smooth]
        counts = (rows > 0).sum(-1)
        scaled = nodes[:, None] ** 2 * rows[rows > 0][None]  # row-major: each bit's cells contiguous
        groups.append((node_weights, scaled, np.concatenate([[0], np.cumsum(counts)[:-1]])))
    chi_square = (1.0 - n / max(t, 1e-3)) / 2.0  # the saddlepoint if T were chi-square(n)
    p = _saddlepoint_tail(t, lambda lam: _square_sum_cgf(lam, n, groups), -20.0, 0.45, float(n), variance,
                          chi_square)
    if smooth.all() or p <= FPR * 1e-3:  # no few-cell bit, or far past the threshold: nothing to gain
        return p
    return min(p, _chernoff_square_sum(t, squares))


ENUMERATED_CELLS = 10


def _chernoff_square_sum(t: float, squares: np.ndarray) -> float:
    """An upper bound on P(T >= t), T = sum_b z_b^2, for bits whose evidence sits on a few cells, where
    chi-square(1) (`_exact_square_sum_pvalue`) gives away most of what the picture shows: a bit seen
    by two equal cells has z^2 = 0 or 2, so 64 such bits all read right (T = 128) happen with
    probability 2^-64 without a mark, where chi-square(64) says 1e-6.

    Chernoff: P(T >= t) <= exp(K(lam) - lam t) for every lam > 0, with K a bound on T's cumulant
    generating function that holds exactly: each bit's ENUMERATED_CELLS heaviest cells give
    A = sum w_i s_i over all their sign patterns, the remaining cells B a sub-Gaussian sum
    (E exp(a B) <= exp(a^2 r / 2), r their sum of w^2), and by the Gaussian trick
    E exp(lam (A + B)^2) <= (1 - 2 lam r)^-1/2 E_A exp(lam A^2 / (1 - 2 lam r)). squares (N, M): w^2
    per bit, each row summing to 1."""
    cells = min(ENUMERATED_CELLS, squares.shape[-1])
    weights = np.sqrt(-np.sort(-np.partition(squares, squares.shape[-1] - cells, axis=-1)[:, -cells:], axis=-1))
    rest = np.clip(1.0 - (weights ** 2).sum(-1), 0.0, None)  # (N,)
    patterns = 1.0 - 2.0 * ((np.arange(2 ** (cells - 1))[:, None] >> np.arange(cells - 1)) & 1)  # the first cell +
    a_squared = ((weights[:, :1] + weights[:, 1:] @ patterns.T) ** 2)[:, None, :]  # (N, 1, patterns)
    top = 0.5 / rest.max() if rest.max() > 0 else math.inf

    def bound(lam: np.ndarray) -> np.ndarray:  # log of the bound at each lam (L,)
        shrink = 1.0 - 2.0 * lam[None, :] * rest[:, None]  # (N, L)
        exponent = lam[None, :, None] * a_squared / shrink[..., None]
        peak = exponent.max(-1)
        log_mean = peak + np.log(np.exp(exponent - peak[..., None]).mean(-1))
        return (log_mean - 0.5 * np.log(shrink)).sum(0) - lam * t

    grid = np.geomspace(1e-3, min(top * (1.0 - 1e-6), 60.0), 32)
    values = bound(grid)
    best = int(values.argmin())
    low, high = grid[max(best - 1, 0)], grid[min(best + 1, len(grid) - 1)]
    for _ in range(16):  # golden section around the best grid point: any lam found is a valid bound
        inner = np.array([high - 0.618 * (high - low), low + 0.618 * (high - low)])
        left, right = bound(inner)
        low, high = (low, inner[1]) if left < right else (inner[0], high)
    return float(min(1.0, math.exp(min(values.min(), float(bound(np.array([0.5 * (low + high)]))[0])))))


def _exact_sum_pvalue(s: float, weights: np.ndarray) -> float:
    """P(S >= s) for S = sum_i v_i s_i, v the weights (any shape), s_i fair random signs."""
    weights = np.abs(np.asarray(weights, dtype=np.float64)).ravel()
    weights = weights[weights > 0]
    if not len(weights):
        return 1.0 if s <= 0 else float(np.finfo(float).tiny)
    limit = 1e4 / weights.max()
    return _saddlepoint_tail(s, lambda lam: _rademacher_cgf(lam, weights), -limit, limit, 0.0, float((weights ** 2).sum()))


def pool(z_list) -> torch.Tensor:
    """Soft bits of K pictures of one asset -> sum_k z_k / sqrt(K): still N(0, 1) per bit under H0
    (independent pictures), while a mark's mean grows as sqrt(K)."""
    values = [torch.as_tensor(z, dtype=torch.float64) for z in z_list]
    if not values:
        raise MeshsealError("no soft bits to pool")
    if len({tuple(v.shape) for v in values}) > 1:
        raise MeshsealError("soft bits to pool must all have the same length")
    return torch.stack(values).sum(0) / math.sqrt(len(values))


def binomial_pvalue(n_agree: int, n_bits: int) -> float:
    """P(X >= n_agree | H0) for X ~ Binomial(N, 1/2): hard bits agreeing with an expected message,
    fair coins under H0 because the keystream whitens every bit."""
    if not 0 <= n_agree <= n_bits:
        raise MeshsealError(f"agreeing bits must be between 0 and {n_bits}, got {n_agree}")
    return sum(math.comb(n_bits, i) for i in range(n_agree, n_bits + 1)) / 2 ** n_bits  # exact, rounded once


def detected(p: float) -> bool:
    """Whether a p-value clears the false-positive rate FPR (one in a million unmarked pictures)."""
    return p <= FPR


__all__ = ["encode", "decode", "Decoded", "Message", "payload_bits", "key_seed", "detection_pvalue",
           "match_pvalue", "pool", "binomial_pvalue", "detected", "FPR", "SCHEMA_VERSION", "SCHEMAS"]
