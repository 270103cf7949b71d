"""Progress bars: tqdm's notebook bar in Jupyter, its text bar elsewhere, none when off."""


def progress_bar(show: bool, **options):
    """A tqdm bar; `show=False` gives a disabled plain bar, so that Jupyter without
    ipywidgets does not warn about a notebook bar nobody asked for."""
    if show:
        from tqdm.auto import tqdm
    else:
        from tqdm import tqdm
    return tqdm(disable=not show, **options)
