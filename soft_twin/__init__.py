"""soft_twin: the rclpy node of the soft continuum robot digital twin.

This file is NOT installed: the installed package ``soft_twin`` gets its
``__init__.py`` from rosidl, which generates ``soft_twin.msg`` and
``soft_twin.srv`` from msg/ and srv/ (see CMakeLists.txt). Keep it free of API.

It only matters when this source folder is imported instead of the installed
package (Python started with the repository root on sys.path, as pytest does
here, see pyproject.toml). Then ``extend_path`` appends every other
``soft_twin`` folder on sys.path, the installed one included, so the generated
``soft_twin.msg`` / ``soft_twin.srv`` modules still import while the
hand-written modules come from these sources.
"""

from pkgutil import extend_path

__path__ = extend_path(__path__, __name__)
