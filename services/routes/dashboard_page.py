"""The dashboard's page, style and script (served by services/routes/dashboard.py; vanilla JS, no build step).

The script reads the JSON API with the session cookie (`credentials: same-origin`; state-changing requests add the
CSRF header `X-NeuMatEx-CSRF: 1`) and follows progress with `EventSource` on `/v1/jobs/{id}/events` (the cookie
goes with it). No API key is ever kept by the page: the login form posts it once to `POST /v1/session`.
"""

from __future__ import annotations

HTML = r"""<!doctype html><html lang="en"><head><meta charset="utf-8"><title>NeuMatEx jobs</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,"><link rel="stylesheet" href="/dashboard.css"></head><body>
<header><h1><a href="#" class="home">NeuMatEx jobs</a></h1><span id="who" class="muted"></span>
<button id="logout" type="button" hidden>log out</button><span id="status" class="err" role="status"></span></header>
<section id="login" hidden><h2>Log in</h2>
<form id="login-form" autocomplete="off"><label>API key <input id="login-key" type="password" size="50"
autocomplete="off" required></label> <button id="login-submit" type="submit">log in</button>
<span id="login-error" class="err"></span></form>
<p class="muted">The key is sent once and exchanged for a session cookie (HttpOnly, SameSite=Strict) that expires;
this page never stores the key. <code>python -m services create-tenant NAME</code> prints a key.</p></section>
<main id="app" hidden>
<section id="list">
<details id="new-job" open><summary>New job: upload a capture</summary>
<form id="upload-form"><p><label>capture zip <input id="up-zip" type="file" accept=".zip,application/zip"></label>
<span class="muted">or</span> <label>a capture folder <input id="up-dir" type="file" webkitdirectory multiple>
</label></p>
<p><label>name <input id="up-name" size="20" placeholder="from the file"></label>
<label>preset <select id="up-preset"><option>tiny</option><option selected>cpu</option><option>gpu</option>
</select></label> <label title="how the material varies over the object: sets the config's variation">material
<select id="up-variation"><option value="" selected>the default: choose on held-out photos</option>
<option value="textured">textured (several materials)</option><option value="uniform">one uniform material</option>
</select></label> <label>config (JSON) <input id="up-config" size="48" value="{}" spellcheck="false"></label>
<button id="up-submit" type="submit">upload and start</button></p>
<p id="up-status" class="muted" data-state="idle"></p></form></details>
<p class="controls"><label>state <select id="f-state"><option value="">all</option><option>queued</option>
<option>running</option><option>completed</option><option>failed</option><option>canceled</option></select></label>
<button id="prev" type="button">&larr; newer</button> <span id="page-info" class="muted"></span>
<button id="next" type="button">older &rarr;</button></p>
<table id="jobs"><thead><tr><th>job</th><th>state</th><th>stage</th><th>progress</th><th>ETA</th><th>TTO</th>
<th>asset</th></tr></thead><tbody id="rows"></tbody></table></section>
<section id="job" hidden><p><a href="#" class="back">&larr; all jobs</a></p><h2 id="j-title"></h2>
<div id="j-failed" class="failbox" hidden></div>
<table class="mt"><tbody id="j-info"></tbody></table>
<p class="actions"><button id="j-cancel" type="button">cancel</button><button id="j-retry" type="button">retry</button>
<a id="j-zip" class="button" hidden>download the asset (zip)</a>
<button id="j-viewer" type="button" disabled>3D viewer</button> <span id="j-viewer-note" class="muted"></span>
<span id="j-act" class="err"></span></p>
<h3>TTO loss and PSNR</h3><div id="j-curve"><span class="muted">no TTO steps yet</span></div>
<h3>Metrics and timings</h3><div id="j-metrics" class="muted">none yet</div>
<h3>Extraction report</h3><p id="report-status" data-loaded="0" data-total="0" data-failed="0" class="muted">
the report appears once the job has completed</p><p><a id="report-open" target="_blank" rel="noopener noreferrer"
hidden>open the report on its own</a></p><iframe id="report" sandbox="allow-same-origin" referrerpolicy="no-referrer"
title="extraction report" hidden></iframe></section>
</main><script src="/dashboard.js"></script></body></html>"""

CSS = r"""body{font:14px system-ui,sans-serif;margin:1.5em 2em;color:#222}
header{display:flex;gap:1em;align-items:baseline}
h1{margin:0 0 .5em}h1 a{color:inherit;text-decoration:none}table{border-collapse:collapse}#jobs{width:100%}
td,th{padding:4px 8px;border-bottom:1px solid #ddd;text-align:left;vertical-align:top}
.bar{background:#eee;width:180px;height:12px;display:inline-block;vertical-align:middle;border-radius:2px}
.fill{background:#3a7;height:12px;border-radius:2px;transition:width .2s}.failed{color:#b00}.completed{color:#370}
.canceled{color:#777}.running{color:#06c}.err{color:#b00;font-size:12px;white-space:pre-wrap}
.failbox{border:1px solid #e99;background:#fff3f3;padding:8px 12px;margin:8px 0;white-space:pre-wrap}
button,.button{margin-right:6px}.button{display:inline-block;padding:2px 8px;border:1px solid #888;border-radius:3px;
background:#f4f4f4;color:#222;text-decoration:none}#report{width:100%;height:600px;border:1px solid #ccc}
.curves{display:flex;gap:16px;flex-wrap:wrap}.curves figure{margin:0}.curves svg{border:1px solid #ddd;
background:#fafafa}.curves figcaption{font-size:12px;color:#555}.muted{color:#666;font-size:12px}
.mt td,.mt th{padding:2px 8px;font-size:13px}details{margin:0 0 1em;padding:4px 8px;border:1px solid #ddd}
summary{cursor:pointer;font-weight:600}.controls label{margin-right:1em}"""

JS = r"""'use strict';
const $=id=>document.getElementById(id);
const ENT={'&':'&amp;','<':'&lt;','>':'&gt;','"':'&quot;',"'":'&#39;'};
function esc(s){return String(s==null?'':s).replace(/[&<>"']/g,c=>ENT[c])}
function fmt(v){return typeof v==='number'?(Number.isInteger(v)?String(v):v.toPrecision(4)):esc(v)}
const TERMINAL=['completed','failed','canceled'];
const CSRF={'X-NeuMatEx-CSRF':'1'};  // state-changing requests made with the session cookie carry it
function utc(t){return t?Date.parse(/[zZ]|[+-]\d\d:?\d\d$/.test(t)?t:t+'Z'):NaN}
class HttpError extends Error{constructor(status,msg){super(msg);this.status=status}}
async function api(path,opts){opts=opts||{};const method=(opts.method||'GET').toUpperCase();
 const headers=Object.assign({},method==='GET'?{}:CSRF,opts.headers||{});
 const r=await fetch(path,{method:method,headers:headers,body:opts.body,credentials:'same-origin'});
 let body=null;try{body=await r.json()}catch(e){}
 const msg=(body&&body.error)||('HTTP '+r.status);
 if(r.status===401&&!opts.quiet){showLogin(msg)}
 if(!r.ok)throw new HttpError(r.status,msg);return body}
// --- login: the key is posted once and exchanged for an HttpOnly session cookie ---------------------------------
let me=null;
async function start(){try{me=await api('/v1/me',{quiet:true})}catch(e){showLogin(e.status===401?'':e.message);return}
 $('login').hidden=true;$('app').hidden=false;$('logout').hidden=false;$('who').textContent='tenant '+me.tenant.name;
 route()}
function showLogin(msg){me=null;closeJob();closeStreams();$('app').hidden=true;$('login').hidden=false;
 $('logout').hidden=true;$('who').textContent='';$('login-error').textContent=msg||'';$('login-key').focus()}
$('login-form').addEventListener('submit',async ev=>{ev.preventDefault();const k=$('login-key').value.trim();
 $('login-key').value='';$('login-error').textContent='';
 try{await api('/v1/session',{method:'POST',headers:{'Content-Type':'application/json'},
  body:JSON.stringify({api_key:k}),quiet:true})}catch(e){$('login-error').textContent=e.message;return}
 start()});
$('logout').addEventListener('click',async()=>{try{await api('/v1/session',{method:'DELETE',quiet:true})}catch(e){}
 showLogin('logged out')});
// --- the list: filters, pages, live progress from the jobs' event streams --------------------------------------
const PAGE=Math.min(100,Math.max(1,Number(new URLSearchParams(location.search).get('per_page'))||20));
const MAX_STREAMS=4;  // a browser opens at most 6 connections to one host over HTTP/1.1
const list={state:'',offset:0};const streams=new Map();const live={};const started={};let listTimer=null;
function onList(){return me&&!$('list').hidden}
function pct(p){return (100*(p||0)).toFixed(0)}
function eta(id,p,state){if(state!=='running'||!(p>0.02))return '';const t0=started[id];if(!(t0>0))return '';
 const s=(Date.now()-t0)/1000*(1-p)/p;return s<1?'':s<90?s.toFixed(0)+' s':(s/60).toFixed(1)+' min'}
function rowHtml(j){const t=(j.metrics&&j.metrics.tto)||{};const p=j.progress||0;
 const tto=t.psnr_batch!=null?('loss '+fmt(t.loss)+', PSNR '+t.psnr_batch.toFixed(2)+' dB'):'';
 const asset=j.state==='completed'?'<a href="/v1/jobs/'+encodeURIComponent(j.id)+'/asset.zip" download="'+esc(j.id)+
  '.zip">zip</a>':'';
 return '<tr data-job="'+esc(j.id)+'" data-state="'+esc(j.state)+'" data-progress="'+p+'" data-events="'+
  (live[j.id]||0)+'"><td><a href="#job/'+encodeURIComponent(j.id)+'">'+esc(j.id)+'</a><div class="muted">'+
  esc(j.capture_id)+' &middot; '+esc(j.preset)+'</div></td><td class="state '+esc(j.state)+'">'+esc(j.state)+
  '</td><td class="stage">'+esc(j.stage)+'</td><td><div class="bar" role="progressbar" aria-valuemin="0" '+
  'aria-valuemax="100" aria-valuenow="'+pct(p)+'"><div class="fill" style="width:'+pct(p)+'%"></div></div> '+
  '<span class="pct">'+pct(p)+'%</span></td><td class="eta">'+(j.eta_s==null?eta(j.id,p,j.state):
  j.eta_s.toFixed(0)+' s')+'</td><td class="tto">'+tto+'</td><td>'+asset+'</td></tr>'+(j.error?
  '<tr class="errrow"><td></td><td colspan="6" class="err">'+esc(j.error)+'</td></tr>':'')}
async function loadList(){if(!onList())return;const q=new URLSearchParams({limit:PAGE,offset:list.offset});
 if(list.state)q.set('state',list.state);let page;
 try{page=await api('/v1/jobs?'+q)}catch(e){$('status').textContent=e.message;return}
 if(!onList())return;$('status').textContent='';
 if(!page.items.length&&list.offset>0&&page.total>0){list.offset=Math.floor((page.total-1)/PAGE)*PAGE;return loadList()}
 for(const j of page.items)if(j.started_at)started[j.id]=utc(j.started_at);
 $('rows').innerHTML=page.items.map(rowHtml).join('')||'<tr><td colspan="7" class="muted">no jobs'+
  (list.state?' '+esc(list.state):'')+'</td></tr>';
 $('page-info').textContent=page.total?(page.offset+1)+'-'+(page.offset+page.items.length)+' of '+page.total:'';
 $('prev').disabled=page.offset===0;$('next').disabled=page.next_offset==null;
 const active=page.items.filter(j=>!TERMINAL.includes(j.state)).map(j=>j.id).slice(0,MAX_STREAMS);
 for(const [id,es] of streams)if(!active.includes(id)){es.close();streams.delete(id)}
 for(const id of active)if(!streams.has(id))watch(id)}
function soon(){clearTimeout(listTimer);listTimer=setTimeout(loadList,150)}
function closeStreams(){for(const es of streams.values())es.close();streams.clear()}
function listen(es,kind,fn){es.addEventListener(kind,ev=>{let d;try{d=JSON.parse(ev.data)}catch(e){return}fn(d)})}
function watch(id){const es=new EventSource('/v1/jobs/'+encodeURIComponent(id)+'/events');streams.set(id,es);
 for(const kind of ['progress','stage','state','requeued'])listen(es,kind,d=>{live[id]=(live[id]||0)+1;update(id,d);
  if(kind==='state'&&TERMINAL.includes(d.state))soon()});
 listen(es,'end',()=>{es.close();streams.delete(id);soon()});
 es.onerror=()=>{if(es.readyState===EventSource.CLOSED)streams.delete(id)}}  // else it reconnects (Last-Event-ID)
function update(id,d){const tr=document.querySelector('tr[data-job="'+CSS.escape(id)+'"]');if(!tr)return;
 tr.dataset.events=live[id]||0;
 if(d.state){tr.dataset.state=d.state;const c=tr.querySelector('.state');c.className='state '+d.state;
  c.textContent=d.state;if(d.state==='running'&&!started[id])started[id]=Date.now()}
 if(d.stage)tr.querySelector('.stage').textContent=d.stage;
 if(typeof d.progress==='number'&&d.progress>=Number(tr.dataset.progress)){tr.dataset.progress=d.progress;
  tr.querySelector('.fill').style.width=pct(d.progress)+'%';tr.querySelector('.pct').textContent=pct(d.progress)+'%';
  tr.querySelector('.bar').setAttribute('aria-valuenow',pct(d.progress))}
 tr.querySelector('.eta').textContent=eta(id,Number(tr.dataset.progress),tr.dataset.state);
 const m=d.metrics;if(d.stage==='tto'&&m&&m.loss!=null&&m.psnr!=null)tr.querySelector('.tto').textContent=
  'step '+m.step+': loss '+fmt(m.loss)+', PSNR '+Number(m.psnr).toFixed(2)+' dB'}
$('f-state').addEventListener('change',()=>{list.state=$('f-state').value;list.offset=0;loadList()});
$('prev').addEventListener('click',()=>{list.offset=Math.max(0,list.offset-PAGE);loadList()});
$('next').addEventListener('click',()=>{list.offset+=PAGE;loadList()});
// --- upload: a zip, or a folder's files (each named by its path), then the job ----------------------------------
function upStatus(text,state){const s=$('up-status');s.textContent=text;s.dataset.state=state}
$('upload-form').addEventListener('submit',async ev=>{ev.preventDefault();let config;
 try{config=JSON.parse($('up-config').value||'{}');if(typeof config!=='object'||Array.isArray(config)||!config)
  throw new Error('it must be a JSON object')}
 catch(e){upStatus('the config is not valid JSON: '+e.message,'error');return}
 if($('up-variation').value)config.variation=$('up-variation').value;
 const zip=$('up-zip').files[0],dir=Array.from($('up-dir').files);
 if(!zip&&!dir.length){upStatus('choose a capture zip or folder first','error');return}
 const name=$('up-name').value.trim()||(zip?zip.name.replace(/\.zip$/i,''):(dir[0].webkitRelativePath||'capture')
  .split('/')[0]);
 $('up-submit').disabled=true;let cap,job;
 try{if(zip){upStatus('uploading '+zip.name+' ('+(zip.size/1e6).toFixed(1)+' MB) ...','uploading');
   cap=await api('/v1/captures?name='+encodeURIComponent(name),{method:'POST',
    headers:{'Content-Type':'application/zip'},body:zip})}
  else{upStatus('uploading '+dir.length+' files ...','uploading');const form=new FormData();
   for(const f of dir)form.append('files',f,f.webkitRelativePath||f.name);
   cap=await api('/v1/captures?name='+encodeURIComponent(name),{method:'POST',body:form})}
  upStatus('capture '+cap.id+' accepted; starting the job ...','creating');
  job=await api('/v1/jobs',{method:'POST',headers:{'Content-Type':'application/json'},
   body:JSON.stringify({capture_id:cap.id,preset:$('up-preset').value,config:config})})}
 catch(e){upStatus('refused: '+e.message,'error');$('up-submit').disabled=false;return}
 $('up-submit').disabled=false;$('up-zip').value='';$('up-dir').value='';
 const s=$('up-status');s.dataset.state='created';s.dataset.job=job.id;
 s.innerHTML='job <a href="#job/'+encodeURIComponent(job.id)+'">'+esc(job.id)+'</a> created ('+esc(job.state)+')';
 list.state='';$('f-state').value='';list.offset=0;loadList()});
// --- the job page ------------------------------------------------------------------------------------------------
let cur=null;  // {id, job, curve: [{step, loss, psnr}], full: from history.json, es: EventSource, report}
let viewerRoute=null;  // whether this API has POST /v1/jobs/{id}/viewer-token (from its OpenAPI schema)
function openJob(id){if(cur&&cur.id===id)return;closeJob();closeStreams();
 cur={id:id,job:null,curve:[],full:false,es:null,report:false};
 $('j-title').textContent=id;$('j-info').innerHTML='';$('j-metrics').textContent='none yet';$('j-act').textContent='';
 $('j-failed').hidden=true;$('j-curve').innerHTML='<span class="muted">no TTO steps yet</span>';$('report').hidden=true;
 $('report').removeAttribute('src');$('report-open').hidden=true;$('j-zip').hidden=true;$('j-viewer').disabled=true;
 $('j-viewer-note').textContent='';setStatus(0,0,0,'the report appears once the job has completed');
 loadJob();follow(cur)}
function closeJob(){if(cur){if(cur.es)cur.es.close();cur=null}}
function row(k,v){return '<tr><th>'+esc(k)+'</th><td>'+v+'</td></tr>'}
async function loadJob(){if(!cur)return;const c=cur;let j;
 try{j=await api('/v1/jobs/'+encodeURIComponent(c.id))}catch(e){$('status').textContent=e.message;return}
 if(c!==cur)return;c.job=j;$('status').textContent='';const p=pct(j.progress);
 $('j-info').innerHTML=row('state','<span id="j-state" class="'+esc(j.state)+'" data-state="'+esc(j.state)+'">'+
  esc(j.state)+'</span>')+row('stage',esc(j.stage)+(j.stages_done.length?' <span class="muted">(done: '+
  j.stages_done.map(esc).join(', ')+')</span>':''))+row('progress','<div class="bar"><div class="fill" id="j-fill" '+
  'style="width:'+p+'%"></div></div> <span id="j-pct">'+p+'%</span>'+(j.eta_s==null?'':', ETA '+j.eta_s.toFixed(0)+
  ' s'))+(j.message?row('message',esc(j.message)):'')+(j.waiting?row('waiting',esc(j.waiting)):'')+
  row('capture',esc(j.capture_id))+row('preset',esc(j.preset)+', queue '+esc(j.queue)+', attempt '+esc(j.attempt))+
  row('created',esc(j.created_at)+(j.finished_at?', finished '+esc(j.finished_at):''));
 const f=$('j-failed');
 if(j.state==='failed'&&j.error){f.hidden=false;f.innerHTML='<strong>This job failed'+(j.stage?' in its '+
  esc(j.stage)+' stage':'')+':</strong> <span id="j-error">'+esc(j.error)+'</span>'+
  '<div class="muted">Fix the capture or the config and upload again, or retry if the cause was passing.</div>'}
 else f.hidden=true;
 const stages=Object.keys(j.metrics||{});
 $('j-metrics').innerHTML=stages.length?'<table class="mt" id="j-metrics-table"><tr><th>stage</th><th>seconds</th>'+
  '<th>metrics</th></tr>'+stages.map(s=>'<tr><th>'+esc(s)+'</th><td>'+(j.timings&&j.timings[s]!=null?
  j.timings[s].toFixed(1):'')+'</td><td>'+Object.entries(j.metrics[s]).filter(([k])=>k!=='seconds').map(([k,v])=>
  esc(k)+' '+(v!==null&&typeof v==='object'?esc(JSON.stringify(v)):fmt(v))).join(', ')+'</td></tr>').join('')+
  '</table>':'none yet';
 $('j-cancel').disabled=TERMINAL.includes(j.state);
 $('j-retry').disabled=!['failed','canceled'].includes(j.state);
 const z=$('j-zip');z.hidden=j.state!=='completed';z.href='/v1/jobs/'+encodeURIComponent(j.id)+'/asset.zip';
 z.setAttribute('download',j.id+'.zip');
 viewerButton(j);
 if(j.state==='completed'&&!c.report){c.report=true;showReport(c);fullCurve(c)}}
async function hasViewer(){if(viewerRoute===null){try{const r=await fetch('/openapi.json');const s=await r.json();
  viewerRoute=!!(s.paths&&s.paths['/v1/jobs/{job_id}/viewer-token'])}catch(e){viewerRoute=false}}return viewerRoute}
async function viewerButton(j){const ok=await hasViewer();if(!cur||cur.id!==j.id)return;const b=$('j-viewer');
 if(!ok){b.disabled=true;$('j-viewer-note').textContent='(the 3D viewer is not available on this server)';return}
 b.disabled=j.state!=='completed';$('j-viewer-note').textContent=j.state==='completed'?'':'(once completed)'}
$('j-viewer').addEventListener('click',async()=>{if(!cur)return;const w=window.open('','_blank');
 try{const t=await api('/v1/jobs/'+encodeURIComponent(cur.id)+'/viewer-token',{method:'POST'});
  if(!w){location.href=t.url;return}w.opener=null;w.location.href=t.url}
 catch(e){if(w)w.close();if(e.status===404&&/^not found$/i.test(e.message)){viewerRoute=false;
   $('j-viewer').disabled=true;$('j-viewer-note').textContent='(the 3D viewer is not available on this server)'}
  else $('j-act').textContent='3D viewer: '+e.message}});
// A completed job's every TTO step: the report's history.json (the progress events are thinned out in time).
async function fullCurve(c){let h;try{h=await api('/v1/jobs/'+encodeURIComponent(c.id)+'/report/history.json')}
 catch(e){return}
 if(c!==cur||!Array.isArray(h)||!h.length)return;c.full=true;
 c.curve=h.map(r=>({step:r.step,loss:r.loss,psnr:r.psnr}));drawCurve(c)}
async function act(what){if(!cur)return;$('j-act').textContent='';const c=cur;
 try{await api('/v1/jobs/'+encodeURIComponent(c.id)+'/'+what,{method:'POST',
   headers:{'Content-Type':'application/json'},body:what==='retry'?'{}':undefined})}
 catch(e){$('j-act').textContent=what+': '+e.message}
 if(c===cur){c.curve=[];c.full=false;c.report=false;follow(c)}loadJob()}
$('j-cancel').addEventListener('click',()=>act('cancel'));
$('j-retry').addEventListener('click',()=>act('retry'));
// The TTO's loss and PSNR per step as the job's progress events carry them (EventSource: the cookie goes along).
function follow(c){if(c.es)c.es.close();const es=new EventSource('/v1/jobs/'+encodeURIComponent(c.id)+'/events');
 c.es=es;
 listen(es,'progress',d=>{if(c!==cur)return;if(typeof d.progress==='number'){$('j-fill')&&($('j-fill').style.width=
   pct(d.progress)+'%');$('j-pct')&&($('j-pct').textContent=pct(d.progress)+'%')}
  const m=d.metrics;if(d.stage!=='tto'||!m||m.step==null||c.full)return;
  if(c.curve.length&&m.step<=c.curve[c.curve.length-1].step)c.curve=c.curve.filter(p=>p.step<m.step);
  c.curve.push({step:m.step,loss:m.loss,psnr:m.psnr});drawCurve(c)});
 for(const kind of ['state','stage','requeued'])listen(es,kind,()=>{if(c===cur)loadJob()});
 listen(es,'end',()=>{es.close();if(c===cur)loadJob()})}
function chart(id,pts,key,label,color,unit){const w=380,h=150,L=56,R=10,T=10,B=26;
 const xs=pts.map(p=>p.step),ys=pts.map(p=>p[key]);const x0=Math.min(...xs),x1=Math.max(...xs);
 let y0=Math.min(...ys),y1=Math.max(...ys);if(y1<=y0){y0-=1e-6;y1+=1e-6}
 const X=s=>(x1>x0?(s-x0)/(x1-x0):0.5)*(w-L-R)+L,Y=v=>h-B-(v-y0)/(y1-y0)*(h-T-B);
 const line=pts.map(p=>X(p.step).toFixed(1)+','+Y(p[key]).toFixed(1)).join(' ');
 return '<figure><svg id="'+id+'" width="'+w+'" height="'+h+'" role="img" aria-label="'+esc(label)+'" data-points="'+
  pts.length+'"><line x1="'+L+'" y1="'+(h-B)+'" x2="'+(w-R)+'" y2="'+(h-B)+'" stroke="#999"/><line x1="'+L+'" y1="'+T+
  '" x2="'+L+'" y2="'+(h-B)+'" stroke="#999"/><text x="'+(L-4)+'" y="'+(T+8)+'" font-size="10" text-anchor="end">'+
  fmt(y1)+'</text><text x="'+(L-4)+'" y="'+(h-B)+'" font-size="10" text-anchor="end">'+fmt(y0)+'</text><text x="'+L+
  '" y="'+(h-8)+'" font-size="10">step '+x0+'</text><text x="'+(w-R)+'" y="'+(h-8)+'" font-size="10" '+
  'text-anchor="end">'+x1+'</text><polyline fill="none" stroke="'+color+'" stroke-width="1.5" points="'+line+
  '"/></svg><figcaption>'+esc(label)+(unit?' ('+unit+')':'')+'</figcaption></figure>'}
function drawCurve(c){const p=c.curve.filter(r=>typeof r.loss==='number'&&typeof r.psnr==='number');if(!p.length)return;
 const last=p[p.length-1];const rows=p.length>10?p.filter((_,i)=>i%Math.ceil(p.length/10)===0||i===p.length-1):p;
 $('j-curve').innerHTML='<div class="curves">'+chart('curve-loss',p,'loss','TTO loss','#c33','')+
  chart('curve-psnr',p,'psnr','batch PSNR','#36c','dB')+'</div><div class="muted">'+p.length+(c.full?
  ' steps (the report\'s history.json)':' steps reported so far')+', last: step '+last.step+', loss '+fmt(last.loss)+
  ', PSNR '+last.psnr.toFixed(2)+' dB</div><details><summary class="muted">values</summary><table class="mt" '+
  'id="curve-values"><tr><th>step</th><th>loss</th><th>PSNR (dB)</th></tr>'+rows.map(r=>'<tr><td>'+r.step+
  '</td><td>'+fmt(r.loss)+'</td><td>'+r.psnr.toFixed(2)+'</td></tr>').join('')+'</table></details>'}
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
// --- routing: #job/<id> or the list ------------------------------------------------------------------------------
function route(){if(!me)return;const m=/^#job\/(.+)$/.exec(location.hash);$('list').hidden=!!m;$('job').hidden=!m;
 if(m)openJob(decodeURIComponent(m[1]));else{closeJob();loadList()}}
window.addEventListener('hashchange',route);
setInterval(()=>{if(!me)return;if(cur)loadJob();else loadList()},4000);
start();
"""
