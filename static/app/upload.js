// Capture zip in (dropped on the page or chosen) -> upload with progress -> POST /jobs ->
// live stage and progress -> the asset id handed to `onAsset`. Its state is on
// document.body.dataset.upload: idle | uploading | processing | done | error.
import { jobErrorMessage, jobUpdates, uploadFile, apiFetch } from './api.js';

export function bindUpload({ dropTarget, input, enhance, bar, label, onAsset, onError, onJobChange }) {
  const setUpload = (state) => { document.body.dataset.upload = state; };
  const show = (fraction, text) => {
    bar.hidden = fraction === null;
    if (fraction !== null) bar.value = Math.max(0, Math.min(1, fraction));
    label.textContent = text;
  };
  setUpload('idle');
  let busy = false;

  async function run(file) {
    if (busy) return;
    busy = true;
    try {
      if (!/\.zip$/i.test(file.name) && file.type !== 'application/zip') {
        throw new Error(`${file.name} is not a .zip: a capture is uploaded as a zip (capture format v1)`);
      }
      setUpload('uploading');
      show(0, `Uploading ${file.name}…`);
      const capture = await uploadFile('captures', file, {
        onProgress: (f) => show(f, `Uploading ${file.name}: ${Math.round(f * 100)} %`),
      });
      show(0, `Capture ${capture.id}: ${capture.cameras} cameras, ${capture.frames} frames. Starting the job…`);
      const job = await apiFetch('jobs', { method: 'POST', json: { capture_id: capture.id, enhance: enhance.checked } });
      setUpload('processing');
      onJobChange?.(job);
      const final = await follow(job, show, onJobChange);
      if (final.state !== 'succeeded') throw new Error(`Job ${final.id}: ${jobErrorMessage(final)}`);
      show(1, `Job ${final.id} done.`);
      await onAsset(final.asset_id, final); // 'done' once the mesh is on screen
      setUpload('done');
    } catch (err) {
      setUpload('error');
      show(null, '');
      onError(err);
    } finally {
      busy = false;
      input.value = '';
    }
  }

  input.addEventListener('change', () => { if (input.files[0]) run(input.files[0]); });
  const over = (on) => (event) => {
    event.preventDefault();
    dropTarget.classList.toggle('drop-over', on);
  };
  window.addEventListener('dragover', over(true));
  window.addEventListener('dragleave', over(false));
  window.addEventListener('drop', (event) => {
    over(false)(event);
    const file = event.dataTransfer?.files?.[0];
    if (file) run(file);
  });
  return { run };
}

async function follow(job, show, onJobChange) {
  let last = job;
  for await (const update of jobUpdates(job.id)) {
    last = update;
    onJobChange?.(update);
    const stage = update.stage ? `${update.stage}` : update.state;
    const fraction = typeof update.progress === 'number' ? update.progress : 0;
    show(fraction, `Job ${update.id}: ${stage} ${Math.round(fraction * 100)} %`);
  }
  return last;
}
