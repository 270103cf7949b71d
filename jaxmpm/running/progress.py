"""Progress bars: tqdm's notebook bar in Jupyter, its text bar elsewhere, none when off."""


def progress_bar(show: bool, **options):
    """A tqdm bar; `show=False` gives a disabled plain bar, so that Jupyter without
    ipywidgets does not warn about a notebook bar nobody asked for."""
    if show:
        from tqdm.auto import tqdm
    else:
        from tqdm import tqdm
    return tqdm(disable=not show, **options)


def restart_clock(bar, done: int):
    """The bar at `done` steps with its clock started now: its rate and time left count
    from here, so that a compile before it does not make them wrong for the rest of the run
    (tqdm averages the rate over the updates)."""
    if bar.disable:
        return
    bar.reset(bar.total)
    bar.initial = bar.n = bar.last_print_n = done
    bar.set_postfix_str("")
