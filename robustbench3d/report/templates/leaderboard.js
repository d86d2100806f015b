(function(){
  var recall = 'R40';
  function key(td, type){
    if(type === 'num'){
      var raw = td.hasAttribute('data-r40') ? td.getAttribute(recall === 'R40' ? 'data-r40' : 'data-r11')
                                            : td.getAttribute('data-v');
      return raw === '' || raw === null ? null : parseFloat(raw);
    }
    return td.getAttribute('data-v') || '';
  }
  function sortTable(th){
    var table = th.closest('table'), body = table.tBodies[0];
    var col = Array.prototype.indexOf.call(th.parentNode.children, th), type = th.getAttribute('data-type');
    var asc = th.getAttribute('aria-sort') !== 'ascending';
    Array.prototype.forEach.call(th.parentNode.children, function(h){ h.removeAttribute('aria-sort'); });
    th.setAttribute('aria-sort', asc ? 'ascending' : 'descending');
    var rows = Array.prototype.slice.call(body.rows).sort(function(a, b){
      var ka = key(a.cells[col], type), kb = key(b.cells[col], type);
      if(ka === null || kb === null){
        if(ka === null && kb === null){ return a.getAttribute('data-i') - b.getAttribute('data-i'); }
        return ka === null ? 1 : -1;
      }
      var c = type === 'num' ? ka - kb : (ka < kb ? -1 : ka > kb ? 1 : 0);
      if(!asc){ c = -c; }
      return c !== 0 ? c : a.getAttribute('data-i') - b.getAttribute('data-i');
    });
    rows.forEach(function(r){ body.appendChild(r); });
  }
  function setRecall(r){
    recall = r;
    document.querySelectorAll('[data-t40]').forEach(function(e){
      e.textContent = e.getAttribute(r === 'R40' ? 'data-t40' : 'data-t11');
    });
    document.querySelectorAll('.recall-label').forEach(function(s){ s.textContent = r; });
    document.querySelectorAll('button[data-recall]').forEach(function(b){
      b.classList.toggle('on', b.getAttribute('data-recall') === r);
      b.setAttribute('aria-pressed', b.getAttribute('data-recall') === r ? 'true' : 'false');
    });
    document.querySelectorAll('table.lb th[aria-sort]').forEach(function(th){
      th.setAttribute('aria-sort', th.getAttribute('aria-sort') === 'ascending' ? 'descending' : 'ascending');
      sortTable(th);
    });
  }
  document.querySelectorAll('table.lb th').forEach(function(th){
    th.addEventListener('click', function(){ sortTable(th); });
  });
  document.querySelectorAll('button[data-recall]').forEach(function(b){
    b.addEventListener('click', function(){ setRecall(b.getAttribute('data-recall')); });
  });
  function showGroup(box){
    var cls = 'show-' + box.getAttribute('data-group');
    document.querySelectorAll('table.lb').forEach(function(t){ t.classList.toggle(cls, box.checked); });
  }
  document.querySelectorAll('input[data-group]').forEach(function(box){
    showGroup(box);  // a state the browser restored on reload
    box.addEventListener('change', function(){ showGroup(box); });
  });
  document.querySelectorAll('a.prov').forEach(function(a){
    a.addEventListener('click', function(){
      var d = document.getElementById(a.getAttribute('href').slice(1));
      if(d){ d.open = true; }
    });
  });
})();
