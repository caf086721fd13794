/**
 * Staff pages: log in, create a tablet, upload a bundle (resumable), follow its job until the
 * model appears or say why it failed.
 */
import * as api from './api.js';
import { el, formatBytes, showError } from './dom.js';
import { pendingUploads, uploadBundle } from './staff/upload.js';

const $ = (id) => document.getElementById(id);
const JOB_POLL_MS = 1500;
let uploadController = null;
let jobTimer = null;

async function whoami() {
  try {
    const user = await api.sessionUser();
    if (!user) throw Object.assign(new Error('not signed in'), { status: 401 });
    $('whoami').textContent = `${user.email} (${user.role})`;
    $('logout').hidden = false;
    $('login-section').hidden = true;
    $('work').hidden = false;
    renderPending();
    return user;
  } catch (err) {
    if (err.status !== 401 && err.status !== 403) showError($('login-error'), err.message);
    $('login-section').hidden = false;
    $('work').hidden = true;
    $('logout').hidden = true;
    $('whoami').textContent = '';
    return null;
  }
}

$('login-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  try {
    await api.login($('email').value.trim(), $('password').value);
    showError($('login-error'), '');
    $('password').value = '';
    await whoami();
  } catch (err) {
    showError($('login-error'), err.status === 401 ? 'Wrong e-mail or password.' : err.message);
  }
});

$('logout').addEventListener('click', async () => {
  await api.logout().catch(() => {});
  await whoami();
});

$('tablet-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const form = new FormData(e.target);
  const fields = {};
  for (const [k, v] of form.entries()) {
    if (k === 'is_public') continue;
    if (String(v).trim()) fields[k] = String(v).trim();
  }
  fields.is_public = e.target.elements.is_public.checked;
  try {
    const tablet = await api.createTablet(fields);
    showError($('tablet-error'), '');
    $('tablet-result').replaceChildren(
      'Created ',
      el('a', { href: `./tablet.html?id=${tablet.id}` }, `${tablet.designation} (id ${tablet.id})`),
      '. ',
    );
    $('upload-tablet').value = String(tablet.id);
  } catch (err) {
    const where = err.problems?.length ? err.problems.map((p) => `${p.where}: ${p.message}`).join('; ') : err.message;
    showError($('tablet-error'), `The tablet was not created: ${where}`);
  }
});

function renderPending() {
  const list = $('pending');
  list.replaceChildren();
  for (const p of pendingUploads(localStorage)) {
    list.append(
      el('li', {}, `Unfinished upload of ${p.name} (${formatBytes(p.size)}) for tablet ${p.tabletId}: choose the same file again to resume. `),
    );
  }
}

function setUploadProgress(sent, total, note) {
  $('upload-progress').hidden = false;
  $('upload-fill').style.width = `${total ? (100 * sent) / total : 0}%`;
  $('upload-label').textContent = `${formatBytes(sent)} of ${formatBytes(total)} — ${note}`;
  $('upload-progress').dataset.sent = String(sent);
  if (note.startsWith('resuming')) $('upload-progress').dataset.resumedFrom = String(sent);
}

$('upload-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const file = $('upload-file').files[0];
  const tabletId = Number($('upload-tablet').value);
  if (!file || !tabletId) return;
  showError($('upload-error'), '');
  $('upload-problems').replaceChildren();
  uploadController = new AbortController();
  $('upload-start').disabled = true;
  $('upload-pause').hidden = false;
  try {
    const { job } = await uploadBundle({
      file,
      tabletId,
      api,
      storage: localStorage,
      signal: uploadController.signal,
      onProgress: setUploadProgress,
    });
    $('upload-label').textContent = `${formatBytes(file.size)} uploaded and accepted.`;
    followJob(job.id, tabletId);
  } catch (err) {
    if (err.name === 'AbortError') {
      showError($('upload-error'), 'Paused. Choose the same file and press Upload to resume.');
    } else {
      showError($('upload-error'), `The upload failed: ${err.message}`);
      for (const p of err.problems ?? []) $('upload-problems').append(el('li', {}, el('code', {}, p.where), ` ${p.message}`));
    }
  } finally {
    $('upload-start').disabled = false;
    $('upload-pause').hidden = true;
    renderPending();
  }
});
$('upload-pause').addEventListener('click', () => uploadController?.abort());

function followJob(jobId, tabletId) {
  clearTimeout(jobTimer);
  $('job-section').hidden = false;
  $('job-id').textContent = String(jobId);
  $('job-done').hidden = true;
  $('job-retry').hidden = true;
  showError($('job-error'), '');
  const poll = async () => {
    try {
      const job = await api.getJob(jobId);
      $('job-state').textContent = job.state;
      $('job-state').dataset.state = job.state;
      $('job-stage').textContent = job.stage ? `(${job.stage})` : '';
      $('job-fill').style.width = `${Math.round((job.progress ?? (job.state === 'succeeded' ? 1 : 0)) * 100)}%`;
      if (job.state === 'succeeded') {
        $('job-done').hidden = false;
        $('job-link').href = `./tablet.html?id=${tabletId}${job.model_id ? `#m=${job.model_id}` : ''}`;
        return;
      }
      if (job.state === 'failed') {
        showError($('job-error'), `The reconstruction failed: ${job.error ?? 'no reason given'}`);
        $('job-retry').hidden = false;
        $('job-retry').onclick = async () => {
          await api.retryJob(jobId).catch((err) => showError($('job-error'), err.message));
          followJob(jobId, tabletId);
        };
        return;
      }
    } catch (err) {
      showError($('job-error'), `Cannot read the job: ${err.message}`);
    }
    jobTimer = setTimeout(poll, JOB_POLL_MS);
  };
  poll();
}

whoami();
