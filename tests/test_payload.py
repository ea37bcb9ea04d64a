"""The payload layer: messages round-trip through keyed BCH codewords, errors up to t are corrected and
more never crash, keys separate, and the p-values are calibrated under the null model."""

import math

import numpy as np
import pytest
import torch
from scipy import stats

from meshseal import MeshsealError
from meshseal import payload
from meshseal.payload import (FPR, Message, binomial_pvalue, decode, detected, detection_pvalue, encode, key_seed,
                              match_pvalue, payload_bits, pool)

T = {64: 5, 32: 3}
GOLDEN_BITS = "0011111000001011101100000110010010100101110110000010110101100111"  # encode("hi!", key="pinned")
GOLDEN_SEED = 5987186459572867590  # key_seed("pinned")
MESSAGES = {
    64: ["", "a", "meow", "a€", "日", 0, 123, 2 ** 32 - 1, Message.raw("01" * 16), Message.id(7), Message.text("7")],
    32: ["", "x", 0, 4095, Message.raw("110010101100"), Message.text("7")],
}


def _soft(bits: torch.Tensor, mu: float = 3.0) -> torch.Tensor:
    return (2 * bits - 1) * mu


def _expected(message):
    """What decode gives back for a message given to encode: (message, kind)."""
    if isinstance(message, Message):
        return message.value, message.kind
    return message, "text" if isinstance(message, str) else "id"


def test_payload_bits_per_model_and_unknown_models():
    assert payload_bits(64) == 32 and payload_bits(32) == 12
    for call in (lambda: payload_bits(48), lambda: encode("a", n_bits=48), lambda: decode(torch.zeros(48))):
        with pytest.raises(MeshsealError, match="no payload schema for a model of 48 bits"):
            call()


def test_code_is_pinned():
    """The generator polynomials and one keyed codeword are the schema: a galois upgrade that changed
    either would make old marks unreadable."""
    assert str(payload._code(64).generator_poly) == ("x^27 + x^22 + x^21 + x^19 + x^18 + x^17 + x^15 + x^8 + x^4 "
                                                      "+ x + 1")
    assert str(payload._code(32).generator_poly) == "x^15 + x^11 + x^10 + x^9 + x^8 + x^7 + x^5 + x^3 + x^2 + x + 1"
    assert (payload._code(64).t, payload._code(32).t) == (5, 3)
    for n_bits, schema in payload.SCHEMAS.items():  # the copies that spare a codeword the galois import
        assert payload.GENERATORS[n_bits] == int(payload._code(n_bits).generator_poly)
        assert (schema.d - 1) // 2 == payload._code(n_bits).t
    bits = "".join(str(int(b)) for b in encode("hi!", key="pinned"))
    assert bits == GOLDEN_BITS
    assert key_seed("pinned") == GOLDEN_SEED


@pytest.mark.parametrize("n_bits", [64, 32])
def test_every_kind_round_trips(n_bits):
    for message in MESSAGES[n_bits]:
        bits = encode(message, key="k", n_bits=n_bits)
        assert bits.shape == (n_bits,) and set(bits.tolist()) <= {0.0, 1.0}
        result = decode(_soft(bits), key="k")
        assert (result.message, result.kind) == _expected(message), message
        assert (result.version, result.errors_corrected, result.codeword_ok) == (payload.SCHEMA_VERSION, 0, True)
        assert result.bits == "".join(str(int(b)) for b in bits)


@pytest.mark.parametrize("n_bits", [64, 32])
def test_up_to_t_flips_are_corrected(n_bits):
    generator = torch.Generator().manual_seed(n_bits)
    for trial in range(10):
        message = MESSAGES[n_bits][trial % len(MESSAGES[n_bits])]
        bits = encode(message, key="k", n_bits=n_bits)
        for flips in range(T[n_bits] + 1):
            where = torch.randperm(n_bits, generator=generator)[:flips]
            noisy = bits.clone()
            noisy[where] = 1 - noisy[where]
            result = decode(_soft(noisy), key="k")
            assert (result.message, result.errors_corrected) == (_expected(message)[0], flips)


@pytest.mark.parametrize("n_bits", [64, 32])
def test_t_plus_one_flips_are_detected_and_more_never_crash(n_bits):
    """The extended code's distance 2t + 2 makes t + 1 errors a hard-decoding failure, never a wrong
    message; beyond that decode returns a result (failed, or some message) without raising. Soft values
    of equal size say nothing about which bits are wrong, so the soft retry names nothing there either."""
    generator = torch.Generator().manual_seed(n_bits + 1)
    for trial in range(20):
        bits = encode(trial, key="k", n_bits=n_bits)
        for flips in (T[n_bits] + 1, T[n_bits] + 2, n_bits // 4, n_bits // 2):
            noisy = bits.clone()
            where = torch.randperm(n_bits, generator=generator)[:flips]
            noisy[where] = 1 - noisy[where]
            soft = _soft(noisy) * torch.rand(n_bits, generator=generator)
            result = decode(soft, key="k")
            assert result.codeword_ok == (result.errors_corrected is not None) == (result.version is not None)
            if flips == T[n_bits] + 1:
                assert not decode(soft, key="k", soft_retry=False).codeword_ok
                assert decode(_soft(noisy), key="k").message is None


@pytest.mark.parametrize("n_bits, mu, least_right, most_wrong, retry", [
    (64, 2.0, 97, 0, False), (64, 1.25, 20, 3, False), (32, 2.0, 95, 0, False),
    (64, 2.0, 99, 0, True), (64, 1.25, 55, 0, True), (64, 1.0, 8, 0, True), (32, 1.5, 97, 0, True)])
def test_decode_rates_under_gaussian_noise(n_bits, mu, least_right, most_wrong, retry):
    """Soft bits +-mu + N(0, 1), 100 seeded draws, hard decoding alone and with the soft retry
    (measured, right / wrong: N = 64, mu = 1.25: 37 / 1 hard, 64 / 0 with the retry and the check of
    hard decodings that corrected several bits; mu = 1.0: 4 / 2 and 9 / 0; N = 32, mu = 1.5: 84 / 0 and
    100 / 0; `python experiments/soft_decoding.py` has the table on more draws)."""
    rng = np.random.default_rng(n_bits)
    right = wrong = 0
    for trial in range(100):
        value = int(rng.integers(0, 2 ** payload_bits(n_bits)))
        z = _soft(encode(value, key="k", n_bits=n_bits), mu).numpy() + rng.standard_normal(n_bits)
        message = decode(z, key="k", soft_retry=retry).message
        right, wrong = right + (message == value), wrong + (message not in (None, value))
    assert right >= least_right and wrong <= most_wrong, (right, wrong)


def test_a_hard_decoding_the_soft_values_contradict_is_refused():
    """A codeword's signs with five bits flipped, the flipped ones loud and the rest faint. Hard decoding
    corrects the five; the soft values say those five are the surest bits, so the corrected codeword is
    not clearly the likeliest and the check refuses it. With the flips faint instead, it is kept."""
    bits = encode(7, key="k")
    noisy = bits.clone()
    where = torch.tensor([2, 9, 23, 37, 58])
    noisy[where] = 1 - noisy[where]
    loud = _soft(noisy, 0.2)
    loud[where] *= 20.0
    assert decode(loud, key="k", soft_retry=False).message == 7
    assert decode(loud, key="k").message is None
    quiet = _soft(noisy, 2.0)
    quiet[where] *= 0.1
    assert decode(quiet, key="k").message == 7


def test_the_soft_retry_reads_what_hard_decoding_cannot_and_only_where_the_soft_values_say_so():
    """Seven bits wrong (past t = 5), each with a small soft value, every other bit clear: the hard
    decoding fails, the soft retry finds the codeword. The same seven at full size: nothing (a codeword
    as near to the signs might be another)."""
    bits = encode("meow", key="k")
    noisy = bits.clone()
    where = torch.tensor([3, 11, 19, 27, 40, 51, 60])
    noisy[where] = 1 - noisy[where]
    soft = _soft(noisy, 2.0)
    soft[where] *= 0.1
    assert decode(soft, key="k", soft_retry=False).message is None
    found = decode(soft, key="k")
    assert (found.message, found.errors_corrected) == ("meow", 7)
    assert decode(_soft(noisy, 2.0), key="k").message is None
    assert decode(soft, key="other").message is None  # under another key the same values are noise


def test_keys_from_text_and_bytes_agree_and_none_is_the_public_key():
    assert torch.equal(encode("ab", key="secret"), encode("ab", key=b"secret"))
    assert torch.equal(encode("ab"), encode("ab", key=payload.DEFAULT_KEY))
    assert key_seed("secret") == key_seed(b"secret") != key_seed("secreT")
    assert 0 <= key_seed() < 2 ** 63
    assert decode(_soft(encode(9, key="secret")), key=b"secret").message == 9
    with pytest.raises(MeshsealError, match="key is empty"):
        encode("ab", key="")
    with pytest.raises(MeshsealError, match="key must be text or bytes"):
        encode("ab", key=5)


def test_two_keys_give_unrelated_bits():
    """Over 200 key pairs and random messages the distance is Binomial(64, 1/2)-like: mean 32, sd 4."""
    rng = np.random.default_rng(4)
    distances = [int((encode(m, key=f"alice{i}") != encode(m, key=f"bob{i}")).sum())
                 for i, m in enumerate(rng.integers(0, 2 ** 32, 200).tolist())]
    assert abs(np.mean(distances) - 32) < 1.5 and 3 < np.std(distances) < 5, (np.mean(distances), np.std(distances))


def test_the_wrong_key_does_not_read_the_message():
    wrong = [decode(_soft(encode(i, key="alice")), key="bob") for i in range(30)]
    assert not any(result.message == i for i, result in enumerate(wrong))
    assert sum(result.codeword_ok for result in wrong) < 15


@pytest.mark.parametrize("message, n_bits, error", [
    ("hello", 64, "text message is 5 bytes in UTF-8; a 64-bit model carries at most 4"),
    ("ab", 32, "text message is 2 bytes in UTF-8; a 32-bit model carries at most 1"),
    ("€€", 64, "6 bytes"),
    ("a\0", 64, "cannot contain NUL"),
    (2 ** 32, 64, "ID must be an integer from 0 to 4294967295 \\(32 bits\\)"),
    (4096, 32, "from 0 to 4095 \\(12 bits\\)"),
    (-1, 64, "ID must be"),
    (True, 64, "message must be text \\(str\\), an ID \\(int\\) or a Message"),
    (Message.raw("0101"), 64, "exactly 32 0s and 1s"),
    (Message.raw("2" * 32), 64, "exactly 32 0s and 1s"),
    (Message.id("12"), 64, "ID must be"),
    (Message("float", 1.5), 64, "kind must be one of raw, text, id"),
])
def test_messages_that_do_not_fit_are_refused(message, n_bits, error):
    with pytest.raises(MeshsealError, match=error):
        encode(message, n_bits=n_bits)


def test_words_that_are_not_valid_messages_decode_to_none():
    schema = payload.SCHEMAS[64]
    assert payload._message(2 << 34 | 1 << 32 | 0x61000000, schema) == (None, None, 2)  # unknown version
    assert payload._message(1 << 34 | 3 << 32, schema) == (None, None, 1)  # reserved kind
    assert payload._message(1 << 34 | 1 << 32 | 0xFF000000, schema) == (None, "text", 1)  # not UTF-8
    assert payload._message(1 << 34 | 1 << 32 | 0x61006200, schema) == (None, "text", 1)  # inner NUL
    assert payload._message(1 << 34 | 1 << 32 | 0x61620000, schema) == ("ab", "text", 1)
    assert payload._message(1 << 14 | 1 << 12 | 0x100, payload.SCHEMAS[32]) == (None, "text", 1)  # spare bits


def test_decode_refuses_bad_soft_bits():
    with pytest.raises(MeshsealError, match="finite"):
        decode(torch.full((64,), float("nan")))
    with pytest.raises(MeshsealError, match="one vector"):
        decode(torch.zeros(2, 64))


def test_decode_takes_tensors_arrays_and_lists_alike():
    soft = _soft(encode("ok", key="k"))
    results = {decode(value, key="k") for value in (soft, soft.numpy(), soft.tolist(), soft.double())}
    assert len(results) == 1 and results.pop().message == "ok"


def test_detection_pvalue_is_uniform_without_a_mark_and_tiny_with_one():
    rng = np.random.default_rng(0)
    null = detection_pvalue(rng.standard_normal((100_000, 64)))
    assert stats.kstest(null, "uniform").pvalue > 0.01
    signs = rng.integers(0, 2, (10_000, 64)) * 2 - 1
    marked = detection_pvalue(signs * 1.5 + rng.standard_normal((10_000, 64)))
    assert (marked < FPR).mean() > 0.99
    assert isinstance(detection_pvalue(rng.standard_normal(64)), float)
    assert 0 < detection_pvalue(np.full(64, 1e3)) < 1e-300


def test_match_pvalue_is_uniform_without_a_mark_and_tiny_with_the_message():
    rng = np.random.default_rng(1)
    expected = rng.integers(0, 2, 64)
    null = match_pvalue(rng.standard_normal((100_000, 64)), expected)
    assert stats.kstest(null, "uniform").pvalue > 0.01
    marked = match_pvalue((2 * expected - 1) * 1.5 + rng.standard_normal((10_000, 64)), expected)
    assert (marked < FPR).mean() > 0.99
    bits = encode("me", key="k")
    z = _soft(bits, 1.0)
    assert match_pvalue(z, bits) == match_pvalue(z, "".join(str(int(b)) for b in bits)) < FPR
    assert match_pvalue(z, 1 - bits) > 1 - FPR
    with pytest.raises(MeshsealError, match="expected 32 bits, but the model reads 64"):
        match_pvalue(z, bits[:32])
    with pytest.raises(MeshsealError, match="expected bits must be 0 or 1"):
        match_pvalue(z, bits * 2)


def _rademacher(weights: np.ndarray, draws: int, rng, chunk: int = 4096) -> np.ndarray:
    """Soft bits z (draws, N) = sum_i w_bi s_i with fair random signs s: the exact null given a picture.
    Drawn in chunks of packed random bits (z = 2 w.b - sum w for bits b), so that memory stays small."""
    unit = (weights / np.sqrt((weights ** 2).sum(-1, keepdims=True)).clip(1e-30)).astype(np.float32)
    n_bits, n_cells = weights.shape
    out = np.empty((draws, n_bits))
    for start in range(0, draws, chunk):
        count = min(chunk, draws - start)
        packed = rng.integers(0, 256, size=(count, n_bits, (n_cells + 7) // 8), dtype=np.uint8)
        bits = np.unpackbits(packed, axis=-1, count=n_cells).astype(np.float32)
        out[start:start + count] = 2.0 * np.einsum("bm,dbm->db", unit, bits) - unit.sum(-1)
    return out


def test_exact_null_matches_simulated_signs_where_the_normal_model_does_not():
    rng = np.random.default_rng(4)
    weights = rng.exponential(size=(64, 60))  # uneven cells (about 20 effective a bit): lighter tails
    weights[:4] = 0.0  # bits the picture does not show: z = 0
    z = _rademacher(weights, 200_000, rng)
    t = (z ** 2).sum(-1)
    s = (z * (2 * (np.arange(64) % 2) - 1)).sum(-1) / 8  # match_pvalue's statistic for bits 0101...
    # Given the weights each p-value is a function of its statistic: p at the empirical (1 - level)
    # quantile of 200,000 null draws must be the level, over the whole range (uniform p-values: a
    # finer check than a KS test on a sample of the p-values) and in the tail.
    for level in (0.9, 0.7, 0.5, 0.3, 0.1, 0.05, 0.01, 1e-3):
        tolerance = dict(abs=0.02) if level >= 0.1 else dict(rel=0.15)
        threshold = np.quantile(t, 1 - level)
        picture = z[np.argmin(np.abs(t - threshold))]
        assert detection_pvalue(picture, weights) == pytest.approx(level, **tolerance)
        if level < 0.01:
            assert detection_pvalue(picture) > 3 * level  # chi-square(64) over-states the tail
        mark = np.quantile(s, 1 - level)
        assert match_pvalue(z[np.argmin(np.abs(s - mark))], np.arange(64) % 2, weights) == pytest.approx(level, **tolerance)


def test_bits_of_few_cells_never_make_the_p_value_too_small():
    """Nearly discrete z^2 (a bit seen by one to a few cells) misleads a saddlepoint; such bits count as
    chi-square(1), whose tail is heavier: the p-value may be conservative, never too small."""
    rng = np.random.default_rng(6)
    weights = np.zeros((64, 12))
    weights[:, 0] = 1.0
    weights[:40, 1:3] = rng.uniform(0.0, 0.2, (40, 2))  # one dominant cell: z^2 near 1
    weights[40:, :12] = rng.exponential(size=(24, 12)) ** 2
    z = _rademacher(weights, 200_000, rng)
    t = (z ** 2).sum(-1)
    for level in (0.05, 1e-3, 1e-4):
        picture = z[np.argmin(np.abs(t - np.quantile(t, 1 - level)))]
        assert level * 0.9 <= detection_pvalue(picture, weights) <= 1.0
    top = z[np.argmax(t)]  # the very top of 200,000 draws: p about 5e-6, not floored to nothing
    assert 2.5e-6 <= detection_pvalue(top, weights) <= 1e-3


def test_exact_null_is_chi_square_for_many_equal_cells_and_handles_the_extremes():
    z = np.random.default_rng(5).standard_normal(64) * 1.4
    assert detection_pvalue(z, np.ones((64, 400))) == pytest.approx(detection_pvalue(z), rel=0.05)
    one_cell = np.zeros((64, 8))
    one_cell[:, 0] = 1.0  # z = +-1 for sure: T = 64 whatever the signs, so it says nothing (p = 1;
    assert detection_pvalue(np.ones(64), one_cell) >= 0.5  # chi-square(64)'s median, near enough here)
    assert 0 < detection_pvalue(np.full(64, 30.0), np.ones((64, 50))) < 1e-300
    assert detection_pvalue(np.zeros(64), np.zeros((64, 5))) == 1.0
    with pytest.raises(MeshsealError, match="do not fit"):
        detection_pvalue(z, np.ones((32, 4)))


def test_pooling_keeps_the_null_and_adds_up_the_mark():
    rng = np.random.default_rng(2)
    pooled = pool(rng.standard_normal((4, 100_000, 64)))
    assert stats.kstest(detection_pvalue(pooled), "uniform").pvalue > 0.01
    signs = rng.integers(0, 2, (10_000, 64)) * 2 - 1
    pictures = [signs * 0.75 + rng.standard_normal((10_000, 64)) for _ in range(4)]
    assert (detection_pvalue(pictures[0]) < FPR).mean() < 0.1
    assert (detection_pvalue(pool(pictures)) < FPR).mean() > 0.99
    assert torch.allclose(pool([torch.ones(64)] * 4), torch.full((64,), 2.0, dtype=torch.float64))
    with pytest.raises(MeshsealError, match="no soft bits"):
        pool([])


def test_binomial_pvalue_is_exact_and_never_anticonservative():
    assert binomial_pvalue(64, 64) == 2.0 ** -64 and binomial_pvalue(0, 64) == 1.0
    assert binomial_pvalue(33, 64) == pytest.approx(sum(math.comb(64, i) for i in range(33, 65)) / 2 ** 64)
    rng = np.random.default_rng(3)
    table = np.array([binomial_pvalue(n, 32) for n in range(33)])
    p = table[rng.binomial(32, 0.5, 100_000)]
    for alpha in (0.01, 0.05, 0.2):
        assert (p <= alpha).mean() <= alpha + 0.005
    with pytest.raises(MeshsealError, match="between 0 and 64"):
        binomial_pvalue(65, 64)


def test_the_pilot_and_the_bits_combine_into_a_valid_p_value_whatever_their_dependence():
    from meshseal.payload import PILOT_SHARE, any_mark_pvalue
    assert any_mark_pvalue(0.3, None) == 0.3 and any_mark_pvalue(2.0, None) == 1.0
    # The pilot's test carries the larger share: a pilot p-value costs less than the bits' one.
    assert any_mark_pvalue(1.0, 1e-7) == pytest.approx(1e-7 / PILOT_SHARE)
    assert any_mark_pvalue(1e-7, 1.0) == pytest.approx(1e-7 / (1.0 - PILOT_SHARE))
    assert any_mark_pvalue(1e-7, 1e-7) < 2e-7 and any_mark_pvalue(0.95, 0.95) == 1.0
    rng = np.random.default_rng(4)
    u, v = rng.random(200_000), rng.random(200_000)
    # Independent, identical and opposed tests: the combination never rejects more than its level.
    for pilot, bits in ((u, v), (u, u), (u, 1.0 - u)):
        combined = np.array([any_mark_pvalue(b, a) for a, b in zip(pilot[:50_000], bits[:50_000])])
        for alpha in (0.01, 0.05, 0.2):
            assert (combined <= alpha).mean() <= alpha + 3 * np.sqrt(alpha / 50_000)


def test_detected_is_the_fpr_threshold():
    assert detected(FPR) and detected(1e-9) and not detected(2e-6)


def test_same_inputs_give_the_same_numbers():
    assert torch.equal(encode("x", key="k"), encode("x", key="k"))
    assert key_seed("k") == key_seed("k")
    z = torch.randn(64, generator=torch.Generator().manual_seed(0))
    assert decode(z, key="k") == decode(z.clone(), key="k")


def _lattice_tail(cells: int) -> np.ndarray:
    """P(T * cells >= k), k = 0, 1, ...: 64 bits of `cells` equal cells each, z^2 = (sum of signs)^2 /
    cells, so T's distribution is an exact convolution."""
    single = np.zeros(cells ** 2 + 1)
    for ones in range(cells + 1):
        single[(2 * ones - cells) ** 2] += math.comb(cells, ones) / 2 ** cells
    pmf = np.array([1.0])
    for _ in range(64):
        pmf = np.convolve(pmf, single)  # T * cells on the integers
    return pmf[::-1].cumsum()[::-1]


@pytest.mark.parametrize("cells", [4, 8, 10, 12])
def test_exact_null_against_an_exact_lattice_distribution(cells):
    """Every bit `cells` equal cells: z^2 = (sum of signs)^2 / cells, so T's distribution is an exact
    convolution. The p-value is never below the truth, and within 5 % of it from 10 cells on."""
    tail = _lattice_tail(cells)
    for level in (1e-3, 1e-6):
        index = int(np.nonzero(tail <= level)[0][0])
        p = detection_pvalue(np.full(64, math.sqrt(index / cells / 64)), np.ones((64, cells)))
        assert p >= tail[index] * (1 - 1e-9)
        if cells >= 10:
            assert p <= 1.05 * tail[index]


@pytest.mark.parametrize("cells", [1, 2, 3, 5])
def test_bits_of_a_few_equal_cells_get_the_lattice_tail_within_a_chernoff_factor(cells):
    """Small objects: every bit seen by 1-5 equal cells. The bound (`_chernoff_square_sum`) is never
    below the exact tail (a convolution) and within a factor 30 of it at 1e-4 to 1e-8, where
    chi-square(1) per bit over-states it by up to 7e4 (two cells at 1e-8). Two cells read right on all
    64 bits happen with probability 2^-64 without a mark, and that is the p-value."""
    tail = _lattice_tail(cells)
    for level in (1e-4, 1e-6, 1e-8):
        if tail[-1] > level:
            continue  # one cell: T = 64 always, no tail at all
        index = int(np.nonzero(tail <= level)[0][0])
        p = detection_pvalue(np.full(64, math.sqrt(index / cells / 64)), np.ones((64, cells)))
        assert tail[index] * (1 - 1e-9) <= p <= 30 * tail[index]
    if cells == 2:
        assert detection_pvalue(np.full(64, math.sqrt(2.0)), np.ones((64, 2))) == pytest.approx(2.0 ** -64, rel=1e-6)


def test_a_codeword_is_recognised_as_the_bch_decoder_would_and_others_go_to_it():
    from meshseal.payload import SCHEMAS, _bch_decode, _code

    rng = np.random.default_rng(0)
    for n_bits in SCHEMAS:
        code = _code(n_bits)
        for trial in range(40):
            data = rng.integers(0, 2, code.k).astype(np.uint8)
            codeword = np.asarray(code.encode(data), dtype=np.uint8)
            word = np.append(codeword, np.uint8(codeword.sum() % 2))
            flips = rng.choice(n_bits, trial % (code.t + 3), replace=False)
            received = word.copy()
            received[flips] ^= 1
            decoded, n_errors = code.decode(received[:-1], output="codeword", errors=True)
            parity = np.uint8(np.asarray(decoded).sum() % 2)
            expected = None if n_errors < 0 or n_errors + (parity != received[-1]) > code.t else \
                np.append(np.asarray(decoded, dtype=np.uint8), parity)
            got = _bch_decode(received)
            assert (got is None) == (expected is None) and (got is None or np.array_equal(got, expected)), (n_bits, flips)
            if len(flips) == 0:
                assert np.array_equal(got, word)


def test_the_codeword_test_is_the_parity_check_matrix_s():
    """`_is_codeword` (g(x) divides the word) says what galois' parity-check matrix says: no syndrome."""
    from meshseal.payload import SCHEMAS, _code, _is_codeword

    rng = np.random.default_rng(1)
    for n_bits in SCHEMAS:
        code = _code(n_bits)
        check = np.asarray(code.H, dtype=np.int64)
        words = [np.asarray(code.encode(rng.integers(0, 2, code.k).astype(np.uint8)), dtype=np.uint8) for _ in range(50)]
        words += [word ^ (rng.random(code.n) < 0.05).astype(np.uint8) for word in words]
        words += [rng.integers(0, 2, code.n).astype(np.uint8) for _ in range(50)]
        for word in words:
            assert _is_codeword(word) == (not (check @ word.astype(np.int64) % 2).any())


@pytest.mark.parametrize("n_bits", [64, 32])
def test_the_table_decoder_answers_as_galois_does(n_bits):
    """`_bm_decode` (syndromes, Berlekamp-Massey and Chien search on log tables) returns galois' codeword
    and error count, or says it cannot decode where galois does, on codewords with 0 to t + 3 flips and on
    random words."""
    from meshseal.payload import _bm_decode, _code, _schema

    code, schema = _code(n_bits), _schema(n_bits)
    rng = np.random.default_rng(7)
    for trial in range(200):
        if trial % 5 == 4:
            word = rng.integers(0, 2, code.n).astype(np.uint8)
        else:
            word = np.asarray(code.encode(rng.integers(0, 2, code.k).astype(np.uint8)), dtype=np.uint8)
            word[rng.choice(code.n, trial % (code.t + 4), replace=False)] ^= 1
        expected, expected_errors = code.decode(word, output="codeword", errors=True)
        got, errors = _bm_decode(word, schema)
        if expected_errors < 0:
            assert errors < 0
        else:
            assert errors == expected_errors and np.array_equal(got, np.asarray(expected, dtype=np.uint8))


def test_the_tails_agree_with_scipy():
    """payload's distribution tails (torch, float64) are scipy.special's to a relative 1e-12, far
    into the tails the p-values reach."""
    from scipy import special

    from meshseal import payload

    x = np.concatenate([np.linspace(-37.0, 37.0, 4001), [-8.5, 0.0, 3.25]])
    assert np.allclose(payload._normal_below(x), special.ndtr(x), rtol=1e-12, atol=0)
    assert isinstance(payload._normal_below(-3.0), float)
    assert payload._normal_below(-30.0) == pytest.approx(special.ndtr(-30.0), rel=1e-12)
    y = np.linspace(-3.0, 500.0, 2001)
    assert np.allclose(payload._erfcx(y), special.erfcx(y), rtol=1e-14, atol=0)
    statistic = np.linspace(10.0, 2000.0, 1001)
    ours, theirs = payload._chi_square_above(64, statistic), special.chdtrc(64, statistic)
    small = theirs < 1e-3  # where a decision lies: the same to rounding (a few 1e-10 apart around the mean)
    assert small.sum() > 500
    assert np.allclose(ours[small], theirs[small], rtol=1e-12, atol=1e-300)
    assert np.allclose(ours, theirs, rtol=1e-8, atol=0)
    for k in (0, 1, 5, 30):
        for mean in (0.05, 1.0, 7.5, 40.0):
            assert payload._poisson_above(k, mean) == pytest.approx(special.pdtrc(k, mean), rel=1e-8)
