from setuptools import setup

setup(
    name="mls-mpm",
    version="0.1.0",
    description="Differentiable 2D and 3D MLS-MPM with hand-written reverse kernels for shape-morphing animation",
    python_requires=">=3.10",
    packages=["mls_mpm", "mls_mpm.bench", "adjoint"],
    license="MIT",
    install_requires=["taichi>=1.7,<1.8", "numpy", "pillow", "scipy", "trimesh", "tomli; python_version<'3.11'",
                      "plyfile", "scikit-image", "imageio-ffmpeg", "threadpoolctl"],
    # trimesh: 3D meshes in; plyfile, scikit-image, imageio-ffmpeg: 3D outputs; threadpoolctl: numpy's BLAS on one
    # thread while Taichi runs (mls_mpm/blas.py)
    extras_require={"test": ["pytest", "pytest-xdist", "pot"]},  # xdist: the suite on every core
    entry_points={"console_scripts": ["mls-mpm = mls_mpm.cli:main"]},
)
