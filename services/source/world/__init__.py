"""The synthetic world's pieces, each by what it is: the route (route.py), a layout's walls,
lamps and look-alikes (layout.py; the campus's in campus.py), the textures (textures.py) and
the revisits its ground truth holds (revisits.py). services/source/synthetic.py renders them
as a frame source."""
