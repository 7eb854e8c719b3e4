"""Mesh previews: scalar colouring reaches the pixels."""
import numpy as np

from simulate.viz import MeshLayer, render_png


def test_scalar_layer_colours_each_end_of_the_colormap(tmp_path):
    import matplotlib.image as mpimg

    # two squares side by side facing the camera (+z), scalar 0 on the left one, 1 on the right
    v = np.array([[-2, 0, 0], [-1, 0, 0], [-1, 1, 0], [-2, 1, 0], [1, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    s = np.array([0, 0, 0, 0, 1, 1, 1, 1], float)
    path = render_png(tmp_path / "p.png", [MeshLayer(v, f, scalars=s, cmap="coolwarm", vmin=0.0, vmax=1.0)],
                      views=(0.0,), elevation=0.0, colorbar_label="value")
    img = mpimg.imread(path)[..., :3]
    red, blue = img[..., 0], img[..., 2]
    assert ((blue > red + 0.3)).sum() > 200, "no pixels in the low (blue) end of coolwarm"
    assert ((red > blue + 0.3)).sum() > 200, "no pixels in the high (red) end of coolwarm"
