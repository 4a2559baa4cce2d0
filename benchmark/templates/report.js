document.querySelectorAll('table.sortable').forEach(function(t){
  t.querySelectorAll('th').forEach(function(th,i){th.addEventListener('click',function(){
    var dir=th.dataset.dir==='asc'?'desc':'asc';
    t.querySelectorAll('th').forEach(function(h){delete h.dataset.dir});th.dataset.dir=dir;
    var body=t.tBodies[0],rows=Array.prototype.slice.call(body.rows);
    function key(r){var c=r.cells[i];if(!c)return '';return c.dataset.v!==undefined?c.dataset.v:c.textContent}
    rows.sort(function(a,b){var x=key(a),y=key(b);if(x===''||y==='')return x===y?0:(x===''?1:-1);
      var nx=parseFloat(x),ny=parseFloat(y),s=(!isNaN(nx)&&!isNaN(ny))?nx-ny:String(x).localeCompare(String(y));
      return dir==='asc'?s:-s});
    rows.forEach(function(r){body.appendChild(r)});});});});
var diff=document.getElementById('diff');
if(diff){diff.addEventListener('change',function(){document.querySelectorAll('img[data-diff]').forEach(
  function(im){im.src=diff.checked?im.dataset.diff:im.dataset.thumb})})}
var box=document.getElementById('lightbox'),big=box.querySelector('img');
document.querySelectorAll('a.zoom').forEach(function(a){a.addEventListener('click',function(ev){
  ev.preventDefault();var im=a.querySelector('img');var showDiff=diff&&diff.checked&&im.dataset.diff;
  big.onerror=function(){big.onerror=null;big.src=im.src};big.src=showDiff?im.dataset.diff:a.getAttribute('href');
  box.style.display='flex'})});
box.addEventListener('click',function(){box.style.display='none'});
document.addEventListener('keydown',function(ev){if(ev.key==='Escape')box.style.display='none'});
