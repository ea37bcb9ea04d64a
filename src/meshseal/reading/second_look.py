"""A second look at a registered picture whose mark was not found: the camera matched block by block
and sharpened on the reading's own residual, then the registration's next-best views, the p-value
paying for every try."""

from __future__ import annotations

from dataclasses import replace

from ..threads import reading_threads
from .read import Reading

SHARPEN_ROUNDS = 2  # a second look sharpens the registered camera again (light refitted) where the first round's reading hints at a mark
LOOK_AGAIN_BELOW = 0.05  # a second look finishes the other views where the first reading's p-value is under this, else those whose rough reading's is
# A second look sharpens the camera only where the first reading's p-value is at most this: the marked
# pictures a second look finds already hint at their mark there (docs/reading.md, stage 7, has the
# pictures it was set on), and an unmarked picture's first p is mostly above it (sharpening would cost
# it its renders for nothing).
SHARPEN_BELOW = 0.5
# Where the first reading's p-value (its stages paid) is at most this and no stage before found the
# mark, the registered camera is nudged NUDGE_STEP px along each way of six moves and each nudge read.
NUDGE_BELOW = 1e-3
NUDGE_STEP = 0.06


def look_again(reader, reading: Reading, original, key=None, expect=None, search: bool = True) -> Reading:
    """A registered reading, looked at again where its mark is not found: first under the registered
    camera matched block by block (`registration.polish_blocks`: a thin or small object whose fine
    texture leaves the polish in a hollow a third of a pixel off), where that fits the picture better,
    then sharpened on the reading's own residual (`registration.sharpen`: a picture whose texture
    aliases loses its mark to a tenth of a pixel of pose error), then under the registration's
    next-best views (`Registration.alternatives`: a near-symmetric shape's twin views fit its
    silhouette and texture alike, and only the keyed mark tells them apart), keeping the camera
    whose reading is likeliest marked. Where the registered camera's reading already hints at a
    mark (p-value under LOOK_AGAIN_BELOW: a twin view of a symmetric asset still reads part of the
    mark) each alternative is finished (refined on the texture) and read; else each is first read
    as refined on its silhouettes alone, and finished only where that rough reading hints at a
    mark, so that unmarked pictures pay little for it. Sharpening runs only where the registered
    camera's p-value is at most SHARPEN_BELOW, and again (light refitted at the sharpened camera) where
    its first reading hints at a mark, SHARPEN_ROUNDS times at most.
    Where none of that found the mark and the first reading's p-value is at most NUDGE_BELOW, the
    registered camera is *nudged* (`registration.nudges`: NUDGE_STEP px each way along six orthogonal
    screen moves, 12 cameras) and each nudge read: after JPEG or a resize the texture-led stages can
    stop a tenth of a pixel off, where a point a few hundredths away reads the mark; the nudges are
    centred on the registered camera, not on the keyed readings' best, so that which cameras are read
    does not depend on the key. The
    p-value pays for all of it (Bonferroni over four stages, each given a quarter: the registered
    camera, the matched and sharpened ones, the nudges, the alternatives): x4 at the registered camera,
    x4(R + 1) at the matched one or a sharpened one of R rounds, x48 at a nudge, x4K at the best of K
    alternatives (x3, x3(R + 1) and x36 without alternatives), so that a
    reading's p-value stays valid however the camera was picked (rough readings only decide what
    to finish). Other readings, and all of them with `search` False (pooling), come back as they
    are, without what a second look needs."""
    if not reading.second_look:
        return reading
    if not search or not reader.method.second_look:
        return replace(reading, second_look=())
    picture = reading.second_look[0]
    with reading_threads(picture.shape[-2] * picture.shape[-1]):
        return _look_again(reader, reading, original, key, expect)


def _look_again(reader, reading: Reading, original, key, expect) -> Reading:
    """`look_again` of a registered reading that a second look may change."""
    from .. import payload
    from .registration import nudges, polish, polish_blocks, sharpen, silhouette_iou

    picture, mask, alternatives = reading.second_look
    method = reader.method
    stages = 4 if alternatives else 3
    first = replace(reading, second_look=(), tries=stages)
    decision = method.decide([first], key, expect)
    if decision.detected:
        return first
    hinted = decision.p_value <= LOOK_AGAIN_BELOW
    best, best_p = first, decision.p_value

    on_cpu, on_device = reader.on_cpu(original), picture.to(reader.device)

    def under(camera, tries: int) -> tuple[Reading, float]:
        camera = camera.to(reader.device)
        other = replace(first, evidence=method.evidence(original, on_device, camera), found=camera, tries=tries)
        return other, method.decide([other], key, expect).p_value

    camera = reading.found.to("cpu")
    moved = stages * (SHARPEN_ROUNDS + 1)  # the matched camera and the sharpened ones: one stage
    matched = polish_blocks(on_cpu, camera, picture, mask[None].float())
    if matched is not None:  # it fits the picture better: sharpening starts there too
        camera = matched
        other, p_value = under(matched, moved)
        if p_value < best_p:
            best, best_p = other, p_value
    for _ in range(SHARPEN_ROUNDS if decision.p_value <= SHARPEN_BELOW else 0):  # each round refits the light at the camera the last one found
        if payload.detected(best_p):
            break
        camera = sharpen(on_cpu, camera, picture, mask[None].float())
        sharpened, p_value = under(camera, moved)
        if p_value < best_p:
            best, best_p = sharpened, p_value
        if payload.detected(p_value) or p_value > LOOK_AGAIN_BELOW:
            break
    if not payload.detected(best_p) and decision.p_value <= NUDGE_BELOW:
        nudged = nudges(on_cpu, reading.found.to("cpu"), mask[None].float(), NUDGE_STEP)
        for index in range(len(nudged)):
            other, p_value = under(nudged[[index]], stages * len(nudged))
            if p_value < best_p:
                best, best_p = other, p_value
    for alternative in alternatives:
        if payload.detected(best_p):
            break  # every stage is paid for, tried or not
        if not (hinted or alternative.finished):
            rough = replace(first, evidence=method.evidence(original, on_device, alternative.rough().to(reader.device)))
            if method.decide([rough], key, expect).p_value > LOOK_AGAIN_BELOW:
                continue
        other, p_value = under(polish(on_cpu, alternative.finish(), picture, mask[None].float()), stages * len(alternatives))
        if p_value < best_p:
            best, best_p = other, p_value
    # Only the kept camera's silhouette overlap is reported: the others are never rendered for it.
    return best if best is first else replace(best, registration_iou=silhouette_iou(on_cpu, best.found.to("cpu"), mask))
