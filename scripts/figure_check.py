"""Checks of a matplotlib figure before it is saved: no two texts overlap (titles, axis labels,
tick labels, legend entries, annotations), measured as the renderer lays them out, and no
axis writes one label at two ticks.

    from figure_check import assert_text_apart
    assert_text_apart(fig, "docs/bench/x.png")   # raises ValueError naming the texts
"""

import matplotlib.text


def undrawn_tick_labels(fig):
    """Tick labels an axis keeps but does not draw: their ticks lie outside its view."""
    hidden = set()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            tol = 1e-9 * max(abs(lo), abs(hi), 1.0)
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                if not (lo - tol <= tick.get_loc() <= hi + tol):
                    hidden.update({id(tick.label1), id(tick.label2)})
    return hidden


def text_boxes(fig):
    """(text, bounding box in display pixels) of every text the figure draws."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    hidden = undrawn_tick_labels(fig)
    boxes = []
    for t in fig.findobj(matplotlib.text.Text):
        if not t.get_visible() or not t.get_text().strip() or id(t) in hidden:
            continue
        boxes.append((t.get_text(), t.get_window_extent(renderer)))
    return boxes


def overlaps(boxes, slack=0.5):
    """Pairs of texts whose boxes overlap by more than `slack` pixels both ways."""
    found = []
    for i, (ta, a) in enumerate(boxes):
        for tb, b in boxes[i + 1:]:
            dx = min(a.x1, b.x1) - max(a.x0, b.x0)
            dy = min(a.y1, b.y1) - max(a.y0, b.y0)
            if dx > slack and dy > slack:
                found.append((ta, tb))
    return found


def repeated_tick_labels(fig):
    """Texts an axis writes at two of its drawn ticks (a log axis labelling "0.01" six times)."""
    hidden = undrawn_tick_labels(fig)
    found = []
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            seen = set()
            for tick in axis.get_major_ticks() + axis.get_minor_ticks():
                label = tick.label1
                text = label.get_text().strip()
                if id(label) in hidden or not label.get_visible() or not text:
                    continue
                if text in seen:
                    found.append(text)
                seen.add(text)
    return found


def assert_text_apart(fig, what):
    """Raises unless every text stands apart and no axis repeats a tick label (the figure is
    laid out first: tick labels exist only once it is drawn)."""
    fig.canvas.draw()
    repeated = repeated_tick_labels(fig)
    if repeated:
        raise ValueError(f"{what}: an axis labels two ticks {repeated[0]!r}")
    found = overlaps(text_boxes(fig))
    if found:
        pairs = "; ".join(f"{a!r} over {b!r}" for a, b in found[:8])
        raise ValueError(f"{what}: texts overlap: {pairs}")


def self_test():
    """The check sees two labels drawn into one, and passes two apart."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots()
    ax.text(0.5, 0.5, "3")
    ax.text(0.5, 0.5, "3")
    if not overlaps(text_boxes(fig)):
        raise AssertionError("figure_check: two labels at one place went unnoticed")
    plt.close(fig)
    fig, ax = plt.subplots()
    ax.text(0.2, 0.5, "3")
    ax.text(0.8, 0.5, "21")
    if overlaps(text_boxes(fig)):
        raise AssertionError("figure_check: labels apart were called overlapping")
    plt.close(fig)
    fig, ax = plt.subplots()
    ax.set_xticks([1, 2, 3], ["0.01", "0.01", "0.02"])
    if repeated_tick_labels(fig) != ["0.01"]:
        raise AssertionError("figure_check: a repeated tick label went unnoticed")
    plt.close(fig)


if __name__ == "__main__":
    self_test()
    print("figure_check: ok (two labels at one place and a repeated tick label are caught, "
          "two labels apart pass)")
