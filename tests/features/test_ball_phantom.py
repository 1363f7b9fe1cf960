"""The ball-phantom check: merged balls count as balls, and most views decide."""

import numpy as np

from ctpipe.features.ball_phantom import ball_phantom_share, looks_like_ball_phantom


def _balls(centres, radius=20.0, size=512, rng=None):
    """Line integrals of solid balls (chord lengths) at ``centres`` (x, y), with a little noise."""
    rows, cols = np.mgrid[:size, :size].astype(np.float64)
    view = np.zeros((size, size))
    for x, y in centres:
        view += 2.0 * np.sqrt(np.clip(radius ** 2 - (cols - x) ** 2 - (rows - y) ** 2, 0.0, None)) * 0.05
    rng = rng or np.random.default_rng(0)
    return view + rng.normal(0.0, 0.005, view.shape)


def _texture(size=512, seed=0):
    """A sample's structure: smoothed noise, no balls."""
    from scipy import ndimage

    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.normal(0.0, 1.0, (size, size)), 6.0) + 2.0


SEPARATE = [(80, 80), (400, 90), (90, 420), (420, 400)]


def test_two_balls_merged_where_they_overlap_count_as_two_balls():
    share, balls = ball_phantom_share(_balls(SEPARATE + [(250, 250), (280, 262)]))
    assert balls == 6 and share > 0.95
    # Without the merged pair's blob the share would be four balls' of six.
    alone, _ = ball_phantom_share(_balls(SEPARATE))
    assert alone > 0.95


def test_a_bar_as_wide_as_a_ball_is_not_taken_for_merged_balls():
    view = _balls(SEPARATE)
    view[240:270, 100:420] += 2.0          # a rod 30 px wide and 320 long: 11 discs' area of its widest
    share, balls = ball_phantom_share(view)
    assert balls == 4 and share < 0.5


def test_a_scan_is_a_ball_phantom_when_most_views_say_so():
    ball = _balls(SEPARATE + [(250, 250)])
    three_of_five = np.stack([ball, _texture(seed=1), ball, _texture(seed=2), ball])
    yes, why = looks_like_ball_phantom(three_of_five)
    assert yes, why
    two_of_five = np.stack([_texture(seed=1), ball, _texture(seed=2), ball, _texture(seed=3)])
    yes, why = looks_like_ball_phantom(two_of_five)
    assert not yes and why.startswith("5 views show ") and why.endswith("holding 50% or more in most views")


def test_a_view_where_every_ball_overlaps_another_still_shows_balls():
    """Seven coated balls at three heights: in some views no ball stands alone. With no round blob
    to set the size, the blobs' own inscribed discs do (0 balls and 0 %, when written)."""
    pairs = [(100, 100), (130, 112), (380, 120), (408, 100), (120, 400), (150, 385), (175, 405)]
    share, balls = ball_phantom_share(_balls(pairs))
    assert balls >= 6 and share > 0.95


def test_elongated_blobs_alone_are_not_taken_for_merged_balls():
    """Where no blob is round, a blob counts as merged balls only where it shows two cores: a
    sample's ellipses (as Shepp-Logan's) have one along their long axis."""
    rows, cols = np.mgrid[:512, :512].astype(np.float64)
    view = np.zeros((512, 512))
    for x, y, a, b in [(120, 120, 40, 22), (380, 140, 50, 25), (150, 380, 35, 20), (380, 380, 45, 30)]:
        view += 0.1 * np.sqrt(np.clip(1.0 - ((cols - x) / a) ** 2 - ((rows - y) / b) ** 2, 0.0, None)) * b
    share, balls = ball_phantom_share(view + np.random.default_rng(1).normal(0.0, 0.005, view.shape))
    assert balls == 0 and share < 0.5


def test_nine_views_are_asked_so_that_three_unlucky_ones_do_not_decide():
    """Seventeen views, four of them (8, 12, 14, 16) showing no balls on their own (merged, or lined up along the
    rays): five views spread over the scan (0, 4, 8, 12, 16) would find three of them; nine find four of nine."""
    ball = _balls(SEPARATE + [(250, 250)])
    views = np.stack([_texture(seed=k) if k in (8, 12, 14, 16) else ball for k in range(17)])
    yes, why = looks_like_ball_phantom(views)
    assert yes and why.startswith("9 views show "), why
    assert not looks_like_ball_phantom(views, views=5)[0]
