"""The start-up shim that defers Open3D's plotly viewer (scanreg._o3d_lazy): Open3D imports without plotly or
dash, and its viewer functions still work when called."""

import subprocess
import sys
import textwrap


def _run(code: str) -> str:
    r = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_open3d_imported_after_scanreg_skips_dash_and_plotly():
    out = _run("""
        import sys
        import scanreg.geometry
        import open3d as o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0, 0, 0], [1, 0, 0]]))
        print(len(pc.points), "dash" in sys.modules, "plotly" in sys.modules)
    """)
    assert out == "2 False False"


def test_plotly_viewer_still_works_through_the_shim():
    # the forwarder imports the real module on first use and gives Open3D's own result
    out = _run("""
        import sys
        import scanreg
        import open3d as o3d
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0, 0, 0], [1, 0, 0], [0, 1, 0]]))
        fig = o3d.visualization.get_plotly_fig([pc])
        print(type(fig).__name__, len(fig.data), "dash" in sys.modules)
        # afterwards Open3D's names are its own functions again, not the module
        m = sys.modules["open3d.visualization.draw_plotly"]
        print(o3d.visualization.draw_plotly is m.draw_plotly, callable(o3d.visualization.draw_plotly))
    """)
    assert out.splitlines() == ["Figure 1 True", "True True"]


def test_without_the_shim_open3d_imports_dash():
    # the shim is what keeps dash out: without scanreg, Open3D imports it (if this fails, drop the shim)
    out = _run("""
        import sys
        import open3d
        print("dash" in sys.modules)
    """)
    assert out == "True"
