"""3D viewers in the report: each exported model in a ``<model-viewer>`` (vendored, works offline from the file
system: the model travels as a data URI in a classic script beside the page, which file:// pages may load where a
fetch of the .glb would be refused). The page keeps a ``#viewer-status`` of how many viewers loaded and failed, which
the browser check (:mod:`.browser`) reads."""

from __future__ import annotations

import base64
import html
import json
import shutil
from pathlib import Path

VENDOR = Path(__file__).resolve().parent / "vendor"
SCRIPT = "model-viewer-umd.min.js"

#: the page's bookkeeping of its viewers (runs after every viewer element exists: the report's last script)
STATUS_JS = """<script>
(function(){
  var st={loaded:0,failed:0,errors:[]};
  window.addEventListener('error',function(e){st.errors.push(String(e.message));upd();});
  function upd(){var s=document.getElementById('viewer-status');if(!s)return;
    var n=document.querySelectorAll('model-viewer[data-model]').length;
    s.dataset.viewers=n;s.dataset.loaded=st.loaded;s.dataset.failed=st.failed;
    s.textContent=st.loaded+' of '+n+' 3D models loaded'+(st.errors.length?'; errors: '+st.errors.join(' | '):'');}
  document.querySelectorAll('model-viewer[data-model]').forEach(function(v){
    v.addEventListener('load',function(){st.loaded++;upd();});
    v.addEventListener('error',function(e){st.failed++;st.errors.push(v.dataset.model+': '+
      JSON.stringify(e.detail&&e.detail.type));console.error('model-viewer '+v.dataset.model+' failed');upd();});
    var src=(window.PHOTOREAL_MODELS||{})[v.dataset.model];
    if(src){v.src=src;}else{st.failed++;st.errors.push(v.dataset.model+': model script missing');}
  });
  upd();
})();
</script>"""


def add_model(out_dir: Path, name: str, glb: Path, orbit: list | None = None) -> str:
    """Copy ``glb`` into ``out_dir/models/`` with its data-URI script; the viewer element's HTML."""
    models = Path(out_dir) / "models"
    models.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(glb, models / f"{name}.glb")
    uri = "data:model/gltf-binary;base64," + base64.b64encode(glb.read_bytes()).decode()
    (models / f"{name}.js").write_text("window.PHOTOREAL_MODELS=window.PHOTOREAL_MODELS||{};"
                                       f"window.PHOTOREAL_MODELS[{json.dumps(name)}]={json.dumps(uri)};\n")
    first = "" if orbit is None else f"camera-orbit='{orbit[0]:.1f}deg {orbit[1]:.1f}deg auto' "
    return (f"<model-viewer data-model='{html.escape(name)}' alt='{html.escape(name)}' camera-controls loading='eager' "
            + first +
            "environment-image='neutral' shadow-intensity='0.6' interaction-prompt='none' "
            "style='width:280px;height:280px;display:inline-block;border:1px solid #ccc;background:#f4f4f4'>"
            "</model-viewer>")


def page_scripts(out_dir: Path) -> tuple[str, str]:
    """(head, end of body) scripts of a report with models; empty strings without any."""
    models = sorted((Path(out_dir) / "models").glob("*.js"))
    if not models:
        return "", ""
    shutil.copyfile(VENDOR / SCRIPT, Path(out_dir) / SCRIPT)
    head = f"<script src='{SCRIPT}'></script>" + "".join(f"<script src='models/{p.name}'></script>" for p in models)
    return head, "<p id='viewer-status' data-viewers='0' data-loaded='0' data-failed='0'></p>" + STATUS_JS
