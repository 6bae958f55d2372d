import json
import sys
from pathlib import Path

# The test writes the paths of files of the lab's, on the host. Every one is tried;
# what happened to each is printed as JSON (the first 100 characters, if it was read).
outcomes = []
for path in json.loads(Path("target.json").read_text()):
    try:
        outcomes.append(Path(path).read_text()[:100])
    except OSError as err:
        outcomes.append(type(err).__name__)
print(json.dumps(outcomes))
sys.exit(3)
