"""GET /: a small dashboard (jobs with stage, progress bar, ETA, errors; the TTO loss and PSNR of a job).
It reads the JSON API with the key the user pastes (kept in the browser's localStorage)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

router = APIRouter(include_in_schema=False)

PAGE = """<!doctype html><html><head><meta charset="utf-8"><title>NeuMatEx jobs</title>
<style>body{font:14px system-ui;margin:2em}table{border-collapse:collapse;width:100%}td,th{padding:4px 8px;
border-bottom:1px solid #ddd;text-align:left}.bar{background:#eee;width:200px;height:12px}.fill{background:#3a7;
height:12px}.failed{color:#b00}.err{color:#b00;font-size:12px;white-space:pre-wrap}</style></head><body>
<h1>NeuMatEx jobs</h1><p>API key: <input id="key" size="50" type="password">
<button onclick="save()">use</button> <span id="status"></span></p>
<table><thead><tr><th>job</th><th>state</th><th>stage</th><th>progress</th><th>ETA</th><th>metrics</th>
<th>asset</th></tr></thead><tbody id="rows"></tbody></table>
<script>
const key=()=>localStorage.getItem('nmxkey')||'';document.getElementById('key').value=key();
function save(){localStorage.setItem('nmxkey',document.getElementById('key').value);load()}
function esc(s){return String(s).replace(/[&<>"]/g,c=>({'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;'}[c]))}
async function load(){const st=document.getElementById('status');
 const r=await fetch('/v1/jobs?limit=100',{headers:{'Authorization':'Bearer '+key()}});
 if(!r.ok){st.textContent=(await r.json()).error||r.status;return}st.textContent='';
 const page=await r.json();document.getElementById('rows').innerHTML=page.items.map(j=>{
  const t=j.metrics.tto||{},m=t.psnr_batch?('TTO loss '+t.loss.toFixed(4)+', PSNR '+t.psnr_batch.toFixed(2)+' dB'):'';
  const a=j.state==='completed'?'<a href="#" onclick="dl(\\''+j.id+'\\');return false">zip</a>':'';
  return '<tr><td>'+esc(j.id)+'</td><td class="'+j.state+'">'+j.state+'</td><td>'+esc(j.stage)+
  '</td><td><div class="bar"><div class="fill" style="width:'+(100*j.progress).toFixed(0)+'%"></div></div>'+
  (100*j.progress).toFixed(0)+'%</td><td>'+(j.eta_s==null?'':j.eta_s.toFixed(0)+' s')+'</td><td>'+m+
  '</td><td>'+a+'</td></tr>'+(j.error?'<tr><td></td><td colspan=6 class="err">'+esc(j.error)+'</td></tr>':'')
 }).join('')}
async function dl(id){const r=await fetch('/v1/jobs/'+id+'/asset.zip',{headers:{'Authorization':'Bearer '+key()}});
 const b=await r.blob();const a=document.createElement('a');a.href=URL.createObjectURL(b);a.download=id+'.zip';
 a.click()}
load();setInterval(load,2000);
</script></body></html>"""


@router.get("/", response_class=HTMLResponse)
def dashboard() -> str:
    return PAGE
