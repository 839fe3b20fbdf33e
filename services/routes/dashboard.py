"""GET /: a small dashboard. The list (jobs with stage, progress bar, ETA, errors; the TTO loss and PSNR) and a job
page per job (`/#job/<id>`): state, stage, progress, message, error, metrics per stage, the TTO's loss/PSNR values
as the progress events carried them, cancel and retry, the asset zip, and the extraction report itself: the
pipeline's own report/index.html in a sandboxed frame, through a short-lived link from POST
/v1/jobs/{id}/report-token (services/routes/reports.py), so there is one renderer of the report, not two.

It reads the JSON API with the key the user pastes (kept in the browser's localStorage); `/#key=<key>` (alone or
after the job: `/#job/<id>&key=<key>`) stores it too and is removed from the address at once. The job page writes
how many of the report's images loaded into `#report-status` (`data-loaded`, `data-total`, `data-failed`)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import HTMLResponse

router = APIRouter(include_in_schema=False)

PAGE = r"""<!doctype html><html><head><meta charset="utf-8"><title>NeuMatEx jobs</title>
<style>body{font:14px system-ui;margin:2em}table{border-collapse:collapse}#list table{width:100%}td,th{padding:4px 8px;
border-bottom:1px solid #ddd;text-align:left;vertical-align:top}.bar{background:#eee;width:200px;height:12px;
display:inline-block;vertical-align:middle}.fill{background:#3a7;height:12px}.failed{color:#b00}.completed{color:#370}
.canceled{color:#777}.err{color:#b00;font-size:12px;white-space:pre-wrap}button{margin-right:6px}
#report{width:100%;height:600px;border:1px solid #ccc}#curve{border:1px solid #ddd;background:#fafafa}
.muted{color:#666;font-size:12px}.mt td,.mt th{padding:2px 8px;font-size:13px}</style></head><body>
<h1><a href="#" style="color:inherit;text-decoration:none">NeuMatEx jobs</a></h1>
<p>API key: <input id="key" size="50" type="password"> <button onclick="save()">use</button>
<span id="status"></span></p>
<div id="list"><table><thead><tr><th>job</th><th>state</th><th>stage</th><th>progress</th><th>ETA</th>
<th>metrics</th><th>asset</th></tr></thead><tbody id="rows"></tbody></table></div>
<div id="job" hidden><p><a href="#">&larr; all jobs</a></p><h2 id="j-title"></h2>
<table class="mt"><tbody id="j-info"></tbody></table>
<p><button id="j-cancel" onclick="act('cancel')">cancel</button><button id="j-retry" onclick="act('retry')">retry
</button><a id="j-zip" href="#" hidden>download the asset (zip)</a> <span id="j-act" class="err"></span></p>
<h3>Metrics</h3><div id="j-metrics" class="muted">none yet</div>
<h3>TTO loss and PSNR</h3><div id="j-curve"><span class="muted">no TTO steps yet</span></div>
<h3>Extraction report</h3><p id="report-status" data-loaded="0" data-total="0" data-failed="0" class="muted">
the report appears once the job has completed</p><p><a id="report-open" target="_blank" rel="noopener noreferrer"
hidden>open the report on its own</a></p><iframe id="report" sandbox="allow-same-origin" referrerpolicy="no-referrer"
title="extraction report" hidden></iframe></div>
<script>
const $=id=>document.getElementById(id);
const ENT={'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;',"'":'&#39;'};
function esc(s){return String(s).replace(/[&<>"']/g,c=>ENT[c])}
function fmt(v){return typeof v==='number'?(Number.isInteger(v)?String(v):v.toPrecision(4)):esc(v)}
const key=()=>localStorage.getItem('nmxkey')||'';
const H=()=>({'Authorization':'Bearer '+key()});
function save(){localStorage.setItem('nmxkey',$('key').value);route()}
async function api(path,opts){const r=await fetch(path,Object.assign({headers:H()},opts||{}));
 let body=null;try{body=await r.json()}catch(e){}
 if(!r.ok)throw new Error((body&&body.error)||('HTTP '+r.status));return body}
// --- the list --------------------------------------------------------------------------------------------------
async function loadList(){const st=$('status');let page;
 try{page=await api('/v1/jobs?limit=100')}catch(e){st.textContent=e.message;return}st.textContent='';
 $('rows').innerHTML=page.items.map(j=>{
  const t=j.metrics.tto||{};
  const m=t.psnr_batch!=null?('TTO loss '+t.loss.toFixed(4)+', PSNR '+t.psnr_batch.toFixed(2)+' dB'):'';
  const a=j.state==='completed'?'<a href="#" onclick="dl(\''+esc(j.id)+'\');return false">zip</a>':'';
  return '<tr><td><a href="#job/'+esc(j.id)+'">'+esc(j.id)+'</a></td><td class="'+esc(j.state)+'">'+esc(j.state)+
  '</td><td>'+esc(j.stage)+'</td><td><div class="bar"><div class="fill" style="width:'+(100*j.progress).toFixed(0)+
  '%"></div></div> '+(100*j.progress).toFixed(0)+'%</td><td>'+(j.eta_s==null?'':j.eta_s.toFixed(0)+' s')+'</td><td>'+m+
  '</td><td>'+a+'</td></tr>'+(j.error?'<tr><td></td><td colspan=6 class="err">'+esc(j.error)+'</td></tr>':'')
 }).join('')}
async function dl(id){const r=await fetch('/v1/jobs/'+encodeURIComponent(id)+'/asset.zip',{headers:H()});
 if(!r.ok){$('j-act').textContent='download failed: HTTP '+r.status;return}
 const b=await r.blob();const a=document.createElement('a');a.href=URL.createObjectURL(b);a.download=id+'.zip';
 a.click()}
// --- the job page ----------------------------------------------------------------------------------------------
let cur=null;  // {id, job, curve: [{step, loss, psnr}], full: from history.json, ctl: AbortController, report}
function openJob(id){if(cur&&cur.id===id)return;closeJob();
 cur={id:id,job:null,curve:[],full:false,ctl:new AbortController(),report:false};
 $('j-title').textContent=id;$('j-info').innerHTML='';$('j-metrics').textContent='none yet';$('j-act').textContent='';
 $('j-curve').innerHTML='<span class="muted">no TTO steps yet</span>';$('report').hidden=true;
 $('report').removeAttribute('src');$('report-open').hidden=true;$('j-zip').hidden=true;
 setStatus(0,0,0,'the report appears once the job has completed');loadJob();follow(cur)}
function closeJob(){if(cur){cur.ctl.abort();cur=null}}
function row(k,v){return '<tr><th>'+esc(k)+'</th><td>'+v+'</td></tr>'}
async function loadJob(){if(!cur)return;const c=cur;let j;
 try{j=await api('/v1/jobs/'+encodeURIComponent(c.id))}catch(e){$('status').textContent=e.message;return}
 if(c!==cur)return;c.job=j;$('status').textContent='';
 const pct=(100*j.progress).toFixed(0);
 $('j-info').innerHTML=row('state','<span id="j-state" class="'+esc(j.state)+'" data-state="'+esc(j.state)+'">'+
  esc(j.state)+'</span>')+row('stage',esc(j.stage)+(j.stages_done.length?' <span class="muted">(done: '+
  j.stages_done.map(esc).join(', ')+')</span>':''))+row('progress','<div class="bar"><div class="fill" style="width:'+
  pct+'%"></div></div> '+pct+'%'+(j.eta_s==null?'':', ETA '+j.eta_s.toFixed(0)+' s'))+
  (j.message?row('message',esc(j.message)):'')+(j.waiting?row('waiting',esc(j.waiting)):'')+
  (j.error?row('error','<span id="j-error" class="err">'+esc(j.error)+'</span>'):'')+
  row('preset',esc(j.preset)+', queue '+esc(j.queue)+', attempt '+esc(j.attempt))+
  row('created',esc(j.created_at)+(j.finished_at?', finished '+esc(j.finished_at):''));
 const stages=Object.keys(j.metrics||{});
 $('j-metrics').innerHTML=stages.length?'<table class="mt">'+stages.map(s=>'<tr><th>'+esc(s)+'</th><td>'+
  Object.entries(j.metrics[s]).map(([k,v])=>esc(k)+' '+fmt(v)).join(', ')+(j.timings&&j.timings[s]!=null?
  ' <span class="muted">('+j.timings[s].toFixed(1)+' s)</span>':'')+'</td></tr>').join('')+'</table>':'none yet';
 $('j-cancel').disabled=!['queued','running'].includes(j.state);
 $('j-retry').disabled=!['failed','canceled'].includes(j.state);
 $('j-zip').hidden=j.state!=='completed';
 if(j.state==='completed'&&!c.report){c.report=true;showReport(c);fullCurve(c)}}
// A completed job's every TTO step: the report's history.json (the progress events are thinned out in time).
async function fullCurve(c){let h;try{h=await api('/v1/jobs/'+encodeURIComponent(c.id)+'/report/history.json')}
 catch(e){return}
 if(c!==cur||!Array.isArray(h)||!h.length)return;c.full=true;
 c.curve=h.map(r=>({step:r.step,loss:r.loss,psnr:r.psnr}));drawCurve(c)}
async function act(what){if(!cur)return;$('j-act').textContent='';
 try{await api('/v1/jobs/'+encodeURIComponent(cur.id)+'/'+what,{method:'POST',
   headers:Object.assign({'Content-Type':'application/json'},H()),body:what==='retry'?'{}':undefined})}
 catch(e){$('j-act').textContent=what+': '+e.message}
 const c=cur;if(c){c.ctl.abort();c.ctl=new AbortController();c.curve=[];c.full=false;c.report=false;follow(c)}loadJob()}
// The TTO's loss and PSNR per step, as the job's progress events carried them (GET /v1/jobs/{id}/events).
async function follow(c){let r;
 try{r=await fetch('/v1/jobs/'+encodeURIComponent(c.id)+'/events',{headers:H(),signal:c.ctl.signal})}catch(e){return}
 if(!r.ok||!r.body)return;const rd=r.body.getReader(),dec=new TextDecoder();let buf='';
 try{for(;;){const {value,done}=await rd.read();if(done)break;buf+=dec.decode(value,{stream:true});let i;
  while((i=buf.indexOf('\n\n'))>=0){const block=buf.slice(0,i);buf=buf.slice(i+2);event(c,block)}}}catch(e){}}
function event(c,block){let kind='',data='';for(const line of block.split('\n')){
  if(line.startsWith('event: '))kind=line.slice(7);else if(line.startsWith('data: '))data+=line.slice(6)}
 if(!data||c!==cur)return;let d;try{d=JSON.parse(data)}catch(e){return}
 if(kind==='progress'&&d.stage==='tto'&&d.metrics&&d.metrics.step!=null&&!c.full){
  if(c.curve.length&&d.metrics.step<=c.curve[c.curve.length-1].step)c.curve=c.curve.filter(p=>p.step<d.metrics.step);
  c.curve.push({step:d.metrics.step,loss:d.metrics.loss,psnr:d.metrics.psnr});drawCurve(c)}
 else if(kind==='state'||kind==='stage'||kind==='end')loadJob()}
function poly(pts,key,w,h){const xs=pts.map(p=>p.step),ys=pts.map(p=>p[key]);
 const x0=Math.min(...xs),x1=Math.max(...xs),y0=Math.min(...ys),y1=Math.max(...ys);
 return pts.map(p=>((x1>x0?(p.step-x0)/(x1-x0):0.5)*(w-20)+10).toFixed(1)+','+
  (h-10-(y1>y0?(p[key]-y0)/(y1-y0):0.5)*(h-20)).toFixed(1)).join(' ')}
function drawCurve(c){const p=c.curve,last=p[p.length-1],w=420,h=120;
 const rows=p.length>12?p.filter((_,i)=>i%Math.ceil(p.length/12)===0||i===p.length-1):p;
 $('j-curve').innerHTML='<svg id="curve" width="'+w+'" height="'+h+'" role="img" aria-label="TTO loss and PSNR">'+
  '<polyline fill="none" stroke="#c33" points="'+poly(p,'loss',w,h)+'"/><polyline fill="none" stroke="#36c" points="'+
  poly(p,'psnr',w,h)+'"/></svg><div class="muted"><span style="color:#c33">loss</span> and <span style="color:#36c">'+
  'batch PSNR</span> per step (each scaled to its range); '+p.length+(c.full?' steps (the report\'s history.json)'
  :' steps reported so far')+', last: step '+last.step+
  ', loss '+fmt(last.loss)+', PSNR '+last.psnr.toFixed(2)+' dB</div><table class="mt" id="curve-values"><tr><th>step'+
  '</th><th>loss</th><th>PSNR (dB)</th></tr>'+rows.map(r=>'<tr><td>'+r.step+'</td><td>'+fmt(r.loss)+'</td><td>'+
  r.psnr.toFixed(2)+'</td></tr>').join('')+'</table>'}
// The report: the pipeline's own page in a sandboxed frame (no scripts), through a short-lived token link.
function setStatus(loaded,total,failed,text){const s=$('report-status');s.dataset.loaded=loaded;s.dataset.total=total;
 s.dataset.failed=failed;s.textContent=text}
async function showReport(c){let t;
 try{t=await api('/v1/jobs/'+encodeURIComponent(c.id)+'/report-token',{method:'POST'})}
 catch(e){setStatus(0,0,0,'no report: '+e.message);return}
 if(c!==cur)return;const f=$('report');f.hidden=false;$('report-open').href=t.url;$('report-open').hidden=false;
 setStatus(0,0,0,'loading the report ...');
 f.onload=async()=>{if(c!==cur)return;let d;try{d=f.contentDocument}catch(e){}
  if(!d){setStatus(0,0,0,'the report was shown but its images cannot be counted here');return}
  const imgs=Array.from(d.images);
  await Promise.all(imgs.map(i=>i.complete?null:new Promise(ok=>{i.addEventListener('load',ok);
   i.addEventListener('error',ok)})));
  if(c!==cur)return;const loaded=imgs.filter(i=>i.complete&&i.naturalWidth>0).length;
  setStatus(loaded,imgs.length,imgs.length-loaded,'report: '+loaded+' of '+imgs.length+' images loaded');
  f.style.height=(d.documentElement.scrollHeight+24)+'px'};
 f.src=t.url}
$('j-zip').onclick=()=>{if(cur)dl(cur.id);return false};
// --- routing: #job/<id>, and #key=<key> to set the key --------------------------------------------------------
function route(){const parts=location.hash.replace(/^#/,'').split('&');let keep=[];
 for(const p of parts){if(p.startsWith('key=')){localStorage.setItem('nmxkey',decodeURIComponent(p.slice(4)))}
  else if(p)keep.push(p)}
 if(keep.length!==parts.filter(p=>p).length)history.replaceState(null,'',location.pathname+(keep.length?'#'+
  keep.join('&'):''));
 $('key').value=key();const m=/^job\/(.+)$/.exec(keep[0]||'');
 $('list').hidden=!!m;$('job').hidden=!m;
 if(m)openJob(decodeURIComponent(m[1]));else{closeJob();loadList()}}
window.addEventListener('hashchange',route);route();
setInterval(()=>{if(cur)loadJob();else loadList()},2000);
</script></body></html>"""


@router.get("/", response_class=HTMLResponse)
def dashboard() -> str:
    return PAGE
