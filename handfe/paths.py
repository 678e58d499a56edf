"""Where the repository's data folders are (the package is installed editable from the repo)."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
ANATOMY_DIR = REPO_ROOT / "anatomy"
SUBJECTS_DIR = REPO_ROOT / "subjects"
GRASPS_DIR = REPO_ROOT / "grasps"
WORKFLOWS_DIR = REPO_ROOT / "workflows"
SENSITIVITY_DIR = REPO_ROOT / "sensitivity"
REFERENCE_DIR = REPO_ROOT / "reference"
RESULTS_DIR = REPO_ROOT / "results"
