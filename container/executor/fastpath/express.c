#include "fastpath.h"

/* Express: the loop thread's chain of async subscription callbacks, in C.
 *
 * Why: a message one node of this process publishes to another is reported
 * by the Notifier at once, and the loop thread takes it and runs its
 * ``async def`` callback's first step without waiting (most callbacks
 * finish in it). Done in Python that costs about 20 calls per message
 * (taking, handing to the lane, admitting, entering the runner's task and
 * context, finishing), more than the publish and the take together. Here it
 * is one call per chain: take what the Notifier reported, admit each message
 * into its callback group's lane, run the first step in an idle runner task
 * of that lane (asyncio's current task and the runner's context, as the
 * Python path does) and release the lane.
 *
 * Only the common case is handled here; everything else is handed to the
 * Python path the executor uses anyway: a lane that is busy, locked by
 * another thread or without an idle runner (``slow``), a callback that
 * suspends or fails (``suspended``, ``failed``), a lane with pending work
 * after the step (``release_pending``), and entities that are not express
 * routes (``take_rest``). The lane's state (its Slots, lanes.c) is read and
 * written only while its lock is free: this thread holds the GIL and calls
 * no Python code in between, so no other thread is inside the lane then.
 *
 * Routes (Route objects by handle address, see lanes.c) are read from the
 * wait set's Routes under its take lock, with its dirty and closed flags,
 * like the Python path.
 *
 * Timers: a 100 Hz timer publishing to another node wakes the loop for a
 * callback or two, and the Python between the wait and the callback (taking
 * the timer, handing it to its lane, admitting, the first step, finishing;
 * about 30 calls) was most of what each wake-up cost after the wait itself.
 * ``call_timers`` calls the ready timers that have a route (the same, with
 * the timer's address first) where the wait set's dispatch
 * takes them, under its locks; ``run_fired`` runs their callbacks as
 * ``drain`` runs a message's, once those locks are released.
 *
 * Ownership: every field is a strong reference set once. ready_queue,
 * eager and done_waiters are Python's containers (asyncio's, the
 * dispatcher's, the executor's), read here by their length only; fired is
 * this object's own list.
 */
typedef struct {
  PyObject_HEAD
  NotifierObject * notifier;
  RoutesObject * routes;  /* the wait set's routes and flags */
  PyObject * take_lock;   /* its take lock: a Lock, taken directly */
  PyObject * loop;
  PyObject * ready_queue; /* asyncio's ready deque: non-empty means asyncio has work */
  PyObject * eager;       /* the dispatcher's eager deque */
  PyObject * run_eager;
  PyObject * enter_task;
  PyObject * leave_task;
  PyObject * on_done;
  PyObject * done_waiters; /* on_done is called only while this is non-empty */
  PyObject * slow;        /* slow(entry, message) */
  PyObject * suspended;   /* suspended(entry, message, runner, coro, yielded, context, started) */
  PyObject * failed;      /* failed(entry, message, error or None) */
  PyObject * release_pending; /* release_pending(lane, marker): the slot goes to waiting work */
  PyObject * take_rest;   /* take_rest([(address, count)]): what has no route */
  PyObject * cancelled_error; /* asyncio.CancelledError: a callback's own cancellation is no error */
  PyObject * fired;       /* timer routes called by call_timers, whose callbacks run_fired runs */
  unsigned long long expressed; /* callbacks run here (tests, diagnostics) */
} ExpressObject;

static int Express_init(ExpressObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {
    "notifier", "routes", "take_lock", "loop", "ready_queue", "eager", "run_eager", "enter_task", "leave_task",
    "on_done", "done_waiters", "slow", "suspended", "failed", "release_pending", "take_rest", "cancelled_error",
    NULL};
  PyObject * notifier, * routes, * take_lock, * given[15];
  PyObject ** fields[15] = {
    &self->loop, &self->ready_queue, &self->eager, &self->run_eager, &self->enter_task, &self->leave_task,
    &self->on_done, &self->done_waiters, &self->slow, &self->suspended, &self->failed, &self->release_pending,
    &self->take_rest, &self->cancelled_error, NULL};
  int i;
  if (!PyArg_ParseTupleAndKeywords(
        args, kwargs, "$O!O!OOOOOOOOOOOOOOO", keywords, &NotifierType, &notifier, &RoutesType, &routes,
        &take_lock, &given[0], &given[1], &given[2], &given[3], &given[4], &given[5], &given[6], &given[7],
        &given[8], &given[9], &given[10], &given[11], &given[12], &given[13])) {
    return -1;
  }
  if (!IS_LOCK(take_lock)) {
    PyErr_SetString(PyExc_TypeError, "Express needs the wait set's take lock to be a _fastpath.Lock");
    return -1;
  }
  Py_XSETREF(self->notifier, (NotifierObject *)Py_NewRef(notifier));
  Py_XSETREF(self->routes, (RoutesObject *)Py_NewRef(routes));
  Py_XSETREF(self->take_lock, Py_NewRef(take_lock));
  for (i = 0; fields[i] != NULL; ++i) {
    Py_XSETREF(*fields[i], Py_NewRef(given[i]));
  }
  Py_XSETREF(self->fired, PyList_New(0));
  return self->fired == NULL ? -1 : 0;
}

static int Express_traverse(ExpressObject * self, visitproc visit, void * arg)
{
  Py_VISIT(self->notifier);
  Py_VISIT(self->routes);
  Py_VISIT(self->release_pending);
  Py_VISIT(self->take_rest);
  Py_VISIT(self->loop);
  Py_VISIT(self->ready_queue);
  Py_VISIT(self->eager);
  Py_VISIT(self->run_eager);
  Py_VISIT(self->enter_task);
  Py_VISIT(self->leave_task);
  Py_VISIT(self->on_done);
  Py_VISIT(self->done_waiters);
  Py_VISIT(self->slow);
  Py_VISIT(self->suspended);
  Py_VISIT(self->failed);
  Py_VISIT(self->cancelled_error);
  Py_VISIT(self->fired);
  Py_VISIT(self->take_lock);
  return 0;
}

static int Express_clear(ExpressObject * self)
{
  Py_CLEAR(self->notifier);
  Py_CLEAR(self->routes);
  Py_CLEAR(self->release_pending);
  Py_CLEAR(self->take_rest);
  Py_CLEAR(self->loop);
  Py_CLEAR(self->ready_queue);
  Py_CLEAR(self->eager);
  Py_CLEAR(self->run_eager);
  Py_CLEAR(self->enter_task);
  Py_CLEAR(self->leave_task);
  Py_CLEAR(self->on_done);
  Py_CLEAR(self->done_waiters);
  Py_CLEAR(self->slow);
  Py_CLEAR(self->suspended);
  Py_CLEAR(self->failed);
  Py_CLEAR(self->cancelled_error);
  Py_CLEAR(self->fired);
  Py_CLEAR(self->take_lock);
  return 0;
}

static void Express_dealloc(ExpressObject * self)
{
  PyObject_GC_UnTrack(self);
  Express_clear(self);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject * call2(PyObject * callable, PyObject * a, PyObject * b)
{
  PyObject * args[2] = {a, b};
  return PyObject_Vectorcall(callable, args, 2, NULL);
}

/* The first step's slot is given back (or, through the Python lane, passed
 * to the work waiting for it): 0, or -1 with an exception set. */
static int release(ExpressObject * self, RouteObject * route)
{
  PyObject * result;
  if (!slots_release_first_step(route->slots)) {
    return 0;
  }
  result = call2(self->release_pending, route->lane, route->marker);
  Py_XDECREF(result);
  return result == NULL ? -1 : 0;
}

/* release(), keeping the exception that is set: the slot goes back whatever
 * failed after the step (a failure of that release is reported as unraisable). */
static void release_keeping_error(ExpressObject * self, RouteObject * route)
{
  PyObject * type, * value, * traceback;
  PyErr_Fetch(&type, &value, &traceback);
  if (release(self, route) < 0) {
    PyErr_WriteUnraisable(route->entity);
  }
  PyErr_Restore(type, value, traceback);
}

/* The first step of a callback, the one both paths run: ``call(*args)`` up
 * to its first suspension, inside ``runner``'s task (asyncio's current task
 * while it runs, as an eager task's is) and in a copy of the runner's
 * context (as each asyncio task gets a copy of the context it was created
 * in: what one callback sets in a ContextVar is not the next one's), with
 * ``current`` as what the runner carries meanwhile (for the watchdog).
 *
 * Returns PYGEN_RETURN (done), PYGEN_NEXT (suspended: *coro, *yielded and
 * *context set, new references), PYGEN_ERROR (the callback failed, in
 * creating its coroutine or in its step: that exception is set), or
 * STEP_BROKEN (this path itself failed, before or after the step: that
 * exception is set, and the step may not have run). */
#define STEP_BROKEN (-2)

static int first_step(
  PyObject * loop, PyObject * enter_task, PyObject * leave_task, RunnerObject * runner, PyObject * current,
  PyObject * call, PyObject * const * args, Py_ssize_t nargs, MeterObject * meter, long long arrived,
  long long * started, PyObject ** coro, PyObject ** yielded, PyObject ** context)
{
  PyObject * result, * type, * value, * traceback;
  PyObject * task = Py_NewRef(runner->task); /* held: the calls below run Python code */
  PySendResult status;
  *coro = *yielded = NULL;
  *started = 0;
  if ((*context = PyContext_Copy(runner->context)) == NULL) {
    Py_DECREF(task);
    return STEP_BROKEN;
  }
  Py_XSETREF(runner->current, Py_NewRef(current));
  if (PyContext_Enter(*context) < 0) {
    goto broken;
  }
  result = call2(enter_task, loop, task);
  if (result == NULL) {
    PyContext_Exit(*context);
    goto broken;
  }
  Py_DECREF(result);
  if (meter != NULL) {
    *started = meter_begin(meter, arrived);
  }
  *coro = PyObject_Vectorcall(call, args, (size_t)nargs, NULL);
  status = *coro != NULL ? PyIter_Send(*coro, Py_None, yielded) : PYGEN_ERROR;
  if (meter != NULL) {
    if (status == PYGEN_NEXT) {
      meter_pause(meter, *started);
    } else {
      meter_end(meter, *started, *started);
    }
  }
  PyErr_Fetch(&type, &value, &traceback);
  result = call2(leave_task, loop, task);
  Py_DECREF(task);
  PyContext_Exit(*context);
  Py_XSETREF(runner->current, Py_NewRef(Py_None));
  if (result == NULL) { /* leaving the task failed: nothing sane is left to do */
    Py_XDECREF(type);
    Py_XDECREF(value);
    Py_XDECREF(traceback);
    Py_CLEAR(*coro);
    Py_CLEAR(*yielded);
    Py_CLEAR(*context);
    return STEP_BROKEN;
  }
  Py_DECREF(result);
  if (status == PYGEN_NEXT) {
    return PYGEN_NEXT;
  }
  Py_CLEAR(*coro);
  Py_CLEAR(*yielded);
  Py_CLEAR(*context);
  if (status == PYGEN_ERROR) {
    PyErr_NormalizeException(&type, &value, &traceback);
    if (value != NULL && traceback != NULL) {
      PyException_SetTraceback(value, traceback);
    }
    PyErr_Restore(type, value, traceback);
  }
  return status;

broken:
  Py_DECREF(task);
  Py_XSETREF(runner->current, Py_NewRef(Py_None));
  Py_CLEAR(*context);
  return STEP_BROKEN;
}

/* A failed first step's error (new reference): None for a callback's own
 * cancellation (it ends that callback only), NULL with KeyboardInterrupt
 * set (that one stops the executor). The exception is consumed. */
static PyObject * step_error(PyObject * cancelled_error)
{
  PyObject * type, * value, * traceback;
  PyErr_Fetch(&type, &value, &traceback);
  if (value != NULL && PyErr_GivenExceptionMatches(value, PyExc_KeyboardInterrupt)) {
    PyErr_Restore(type, value, traceback);
    return NULL;
  }
  Py_XDECREF(type);
  Py_XDECREF(traceback);
  if (value == NULL || PyErr_GivenExceptionMatches(value, cancelled_error)) {
    Py_XDECREF(value);
    Py_RETURN_NONE;
  }
  return value;
}

/* Run one taken message's callback (``message`` NULL: a called timer's,
 * without arguments): 0, or -1 with an exception set (one that must stop the
 * executor: KeyboardInterrupt, or a failure of this path). The hand-overs to
 * Python get None for a timer's message. */
static int run_one(ExpressObject * self, RouteObject * route, PyObject * message)
{
  PyObject * given = message != NULL ? message : Py_None;
  PyObject * entry = route->entry;
  PyObject * callback, * coro, * yielded, * context, * result;
  RunnerObject * runner;
  Py_ssize_t waiting;
  long long started;
  int status;

  if (route->token->retired) {
    return 0; /* its entity or node left: dropped, as rclpy drops it */
  }
  if ((result = slots_admit_first_step(route->slots)) == NULL) {
    return -1;
  }
  if (result == Py_None) {
    Py_DECREF(result);
    result = call2(self->slow, entry, given);
    Py_XDECREF(result);
    return result == NULL ? -1 : 0;
  }
  runner = (RunnerObject *)result;
  callback = PyObject_GetAttr(route->entity, route->callback);
  status = callback == NULL ? STEP_BROKEN : first_step(
    self->loop, self->enter_task, self->leave_task, runner, route->marker, callback, &message,
    message != NULL ? 1 : 0, ((WorkObject *)route->marker)->meter, route->arrived, &started, &coro, &yielded,
    &context);
  Py_XDECREF(callback);
  if (status == STEP_BROKEN) {
    slots_undo_first_step(route->slots);
    Py_DECREF(runner);
    return -1;
  }
  self->expressed++;
  /* Until a hook (suspended, failed) takes the work, the slot is this
   * path's: every way out gives it back. */
  if (status == PYGEN_RETURN) {
    Py_DECREF(runner);
    waiting = PyObject_Length(self->done_waiters);
    if (waiting != 0) {
      result = waiting > 0 ? PyObject_CallNoArgs(self->on_done) : NULL;
      Py_XDECREF(result);
      if (result == NULL) {
        release_keeping_error(self, route);
        return -1;
      }
    }
    return release(self, route);
  }
  if (status == PYGEN_NEXT) {
    PyObject * start = PyLong_FromLongLong(started);
    PyObject * args[7] = {entry, given, (PyObject *)runner, coro, yielded, context, start};
    if (start == NULL) {
      release_keeping_error(self, route);
      result = NULL;
    } else {
      /* The Python lane's from here: it counts the work as started, and
       * the runner that finishes it gives the slot back. */
      result = PyObject_Vectorcall(self->suspended, args, 7, NULL);
    }
    Py_XDECREF(start);
    Py_DECREF(coro);
    Py_DECREF(yielded);
    Py_DECREF(context);
    Py_DECREF(runner);
    Py_XDECREF(result);
    return result == NULL ? -1 : 0;
  }
  Py_DECREF(runner);
  if ((result = step_error(self->cancelled_error)) == NULL) {
    release_keeping_error(self, route); /* KeyboardInterrupt: it stops the executor, the group stays usable */
    return -1;
  }
  {
    PyObject * args[3] = {entry, given, result};
    PyObject * told = PyObject_Vectorcall(self->failed, args, 3, NULL);
    Py_DECREF(result);
    Py_XDECREF(told);
    return told == NULL ? -1 : 0;
  }
}

/* first_step(loop, enter_task, leave_task, cancelled_error, runner, work) ->
 * None | BaseException | (coro, yielded, context): the Python lanes' first
 * step of async work, the same as the chain's: done (None), failed (the
 * error), or suspended. Raises KeyboardInterrupt, and what breaks the path. */
static PyObject * first_step_py(PyObject * Py_UNUSED(module), PyObject * const * args, Py_ssize_t nargs)
{
  RunnerObject * runner;
  WorkObject * work;
  PyObject * coro, * yielded, * context, * call_args;
  int status;
  if (nargs != 6 || !PyObject_TypeCheck(args[4], &RunnerType) || !PyObject_TypeCheck(args[5], &WorkType)) {
    PyErr_SetString(PyExc_TypeError, "first_step(loop, enter_task, leave_task, cancelled_error, runner, work)");
    return NULL;
  }
  runner = (RunnerObject *)args[4];
  work = (WorkObject *)args[5];
  call_args = work->args;
  status = first_step(
    args[0], args[1], args[2], runner, (PyObject *)work, work->call, &PyTuple_GET_ITEM(call_args, 0),
    PyTuple_GET_SIZE(call_args), work->meter, work->arrived, &work->started, &coro, &yielded, &context);
  if (status == STEP_BROKEN) {
    return NULL;
  }
  if (status == PYGEN_RETURN) {
    Py_RETURN_NONE;
  }
  if (status == PYGEN_NEXT) {
    return Py_BuildValue("(NNN)", coro, yielded, context);
  }
  return step_error(args[3]);
}

PyMethodDef express_functions[] = {
  {"first_step", (PyCFunction)(void (*)(void))first_step_py, METH_FASTCALL,
   "first_step(loop, enter_task, leave_task, cancelled_error, runner, work) -> None | BaseException | "
   "(coro, yielded, context): async work up to its first suspension in runner's task (done, failed, suspended)"},
  {NULL, NULL, 0, NULL},
};

/* Take what the notifier reported (into ``batch``: route, message, ...) under
 * the take lock; 1 taken, 0 nothing to do (stop), -1 error, -2 a take failed
 * (its exception set; everything else reported was taken). Entities that are
 * not routes go through the wait set's Python ``_take_ready``. */
static int take_batch(ExpressObject * self, PyObject * batch)
{
  PyObject * routes = NULL, * rest = NULL;
  uintptr_t inline_keys[REPORTED_INLINE];
  size_t inline_counts[REPORTED_INLINE];
  uintptr_t * keys = inline_keys;
  size_t * counts = inline_counts;
  PyObject * result, * type = NULL, * value = NULL, * traceback = NULL;
  Py_ssize_t i, n;
  int status = 1;
  long long now = monotonic_ns();

  if (!lock_try((LockObject *)self->take_lock)) {
    /* A worker is carrying: whoever holds it takes what is plain; the
     * caller's next round (the Python path) takes the rest. */
    return 0;
  }
  if (self->routes->closed || self->routes->dirty) {
    status = 0;
    goto out;
  }
  routes = Py_NewRef(self->routes->subscriptions);
  if ((n = notifier_take_reported(self->notifier, &keys, &counts, inline_keys, inline_counts)) < 0) {
    status = -1;
    goto out;
  }
  for (i = 0; i < n; ++i) {
    PyObject * key = PyLong_FromUnsignedLongLong((unsigned long long)keys[i]);
    PyObject * route = key != NULL ? PyDict_GetItemWithError(routes, key) : NULL;
    size_t j;
    if (route == NULL) {
      PyObject * pair;
      if (PyErr_Occurred()) {
        Py_XDECREF(key);
        status = -1;
        goto out;
      }
      pair = Py_BuildValue("(Nn)", key, (Py_ssize_t)counts[i]);
      if (pair == NULL || (rest == NULL && (rest = PyList_New(0)) == NULL) || PyList_Append(rest, pair) < 0) {
        Py_XDECREF(pair);
        status = -1;
        goto out;
      }
      Py_DECREF(pair);
      continue;
    }
    Py_DECREF(key);
    if (!PyObject_TypeCheck(route, &RouteType) || !PyObject_TypeCheck(((RouteObject *)route)->first, &TakerType)) {
      PyErr_SetString(PyExc_TypeError, "a subscription's route is a Route whose first is a Taker");
      status = -1;
      goto out;
    }
    /* Held: a take converts the message with its type's Python code. */
    Py_INCREF(route);
    for (j = 0; j < counts[i]; ++j) {
      PyObject * message;
      ((RouteObject *)route)->arrived = now;
      message = taker_take((TakerObject *)((RouteObject *)route)->first, 0);
      if (message == NULL) {
        /* The rest of what was reported is taken all the same (its counts
         * were taken from the notifier): run it, then report the first error. */
        if (type == NULL && value == NULL) {
          PyErr_Fetch(&type, &value, &traceback);
        } else {
          PyErr_Clear();
        }
        break;
      }
      if (message == Py_None) {
        Py_DECREF(message);
        break;
      }
      if (PyList_Append(batch, route) < 0 || PyList_Append(batch, message) < 0) {
        Py_DECREF(message);
        Py_DECREF(route);
        status = -1;
        goto out;
      }
      Py_DECREF(message);
    }
    Py_DECREF(route);
  }
  if (rest != NULL) {
    result = PyObject_CallOneArg(self->take_rest, rest);
    if (result == NULL) {
      status = -1;
    }
    Py_XDECREF(result);
  }
out:
  Py_XDECREF(routes);
  if (keys != inline_keys) {
    free(keys);
    free(counts);
  }
  Py_XDECREF(rest);
  lock_release((LockObject *)self->take_lock);
  if (type != NULL || value != NULL) {
    /* A take failed: the caller runs the batch, then raises this. */
    PyErr_Restore(type, value, traceback);
    return -2;
  }
  return status;
}

/* drain(deadline_ns) -> bool: take and run what the notifier reports until
 * nothing is, the deadline (the next poll of timers) passes, or asyncio has
 * work of its own. False: the take lock was busy (take the Python way). */
static PyObject * Express_drain(ExpressObject * self, PyObject * arg)
{
  long long deadline = PyLong_AsLongLong(arg);
  PyObject * batch;
  if (deadline == -1 && PyErr_Occurred()) {
    return NULL;
  }
  batch = PyList_New(0);
  if (batch == NULL) {
    return NULL;
  }
  for (;;) {
    Py_ssize_t i, n, queued;
    int status;
    if (!atomic_load(&self->notifier->pending) || monotonic_ns() >= deadline) {
      break;
    }
    queued = PyObject_Length(self->ready_queue);
    if (queued != 0) {
      if (queued < 0) {
        Py_DECREF(batch);
        return NULL;
      }
      break;
    }
    status = take_batch(self, batch);
    if (status == 0) {
      Py_DECREF(batch);
      Py_RETURN_FALSE;
    }
    {
      /* A failed take (-2) still runs what was taken before it. */
      PyObject * et = NULL, * ev = NULL, * tb = NULL;
      if (status == -2) {
        PyErr_Fetch(&et, &ev, &tb);
      }
      n = PyList_GET_SIZE(batch);
      for (i = 0; i + 1 < n && status != -1; i += 2) {
        /* The batch is this call's own list; the pair is held all the same
         * while the callback runs (any code). */
        PyObject * route = Py_NewRef(PyList_GET_ITEM(batch, i));
        PyObject * message = Py_NewRef(PyList_GET_ITEM(batch, i + 1));
        if (run_one(self, (RouteObject *)route, message) < 0) {
          status = -1;
        }
        Py_DECREF(message);
        Py_DECREF(route);
      }
      if (status == -1) {
        Py_XDECREF(et);
        Py_XDECREF(ev);
        Py_XDECREF(tb);
      } else if (PyList_SetSlice(batch, 0, n, NULL) < 0) {
        status = -1;
      } else if (status == -2) {
        PyErr_Restore(et, ev, tb);
      }
    }
    if (status < 0) {
      Py_DECREF(batch);
      return NULL;
    }
    queued = PyObject_Length(self->eager);
    if (queued > 0) {
      PyObject * result = PyObject_CallNoArgs(self->run_eager);
      if (result == NULL) {
        Py_DECREF(batch);
        return NULL;
      }
      Py_DECREF(result);
    } else if (queued < 0) {
      Py_DECREF(batch);
      return NULL;
    }
  }
  Py_DECREF(batch);
  Py_RETURN_TRUE;
}

/* call_timers(routes, ready) -> list: call (as rcl_timer_call) each ready
 * timer that has a route, keeping the route for run_fired; the addresses
 * left to the Python path: no route, or anything unusual about the timer
 * (not ready after all, cancelled, an rcl error), which rclpy's own calls
 * there handle and report. Called under the wait set's take lock, with the
 * table whose handles keep the timers alive: no Python code runs here. */
static PyObject * Express_call_timers(ExpressObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  PyObject * routes, * ready, * rest;
  Py_ssize_t i, n;
  if (nargs != 2 || !PyDict_Check(args[0])) {
    PyErr_SetString(PyExc_TypeError, "call_timers(routes: dict, ready: iterable)");
    return NULL;
  }
  routes = args[0];
  if ((ready = PySequence_Fast(args[1], "call_timers: ready must be iterable")) == NULL) {
    return NULL;
  }
  if ((rest = PyList_New(0)) == NULL) {
    Py_DECREF(ready);
    return NULL;
  }
  n = PySequence_Fast_GET_SIZE(ready);
  for (i = 0; i < n; ++i) {
    PyObject * key = PySequence_Fast_GET_ITEM(ready, i);
    PyObject * route = PyDict_GetItemWithError(routes, key);
    rcl_timer_t * timer;
    bool is_ready = false;
    int64_t until = 0;
    if (route == NULL) {
      if (PyErr_Occurred() || PyList_Append(rest, key) < 0) {
        goto fail;
      }
      continue;
    }
    if (!PyObject_TypeCheck(route, &RouteType)) {
      PyErr_SetString(PyExc_TypeError, "a timer's route is a Route");
      goto fail;
    }
    timer = (rcl_timer_t *)((RouteObject *)route)->timer.pointer;
    if (timer == NULL) {
      PyErr_SetString(PyExc_TypeError, "a timer's route holds its handle");
      goto fail;
    }
    /* Its due time, for its lateness: it was due `until` ago (until <= 0). */
    if (rcl_timer_get_time_until_next_call(timer, &until) != RCL_RET_OK) {
      rcl_reset_error();
      until = 0;
    }
    ((RouteObject *)route)->arrived = monotonic_ns() + (until < 0 ? until : 0);
    if (rcl_timer_is_ready(timer, &is_ready) != RCL_RET_OK || !is_ready || rcl_timer_call(timer) != RCL_RET_OK) {
      rcl_reset_error();
      if (PyList_Append(rest, key) < 0) {
        goto fail;
      }
      continue;
    }
    if (PyList_Append(self->fired, route) < 0) {
      goto fail;
    }
  }
  Py_DECREF(ready);
  return rest;

fail:
  Py_DECREF(ready);
  Py_DECREF(rest);
  return NULL;
}

/* run_fired() -> None: run the callbacks of the timers call_timers called,
 * as drain runs a message's. Outside the wait set's locks (user code runs).
 * What an error stops before is kept for the next call. */
static PyObject * Express_run_fired(ExpressObject * self, PyObject * Py_UNUSED(ignored))
{
  PyObject * fired = self->fired, * fresh;
  Py_ssize_t i, n = PyList_GET_SIZE(fired);
  if (n == 0) {
    Py_RETURN_NONE;
  }
  if ((fresh = PyList_New(0)) == NULL) {
    return NULL;
  }
  self->fired = fresh; /* callbacks may fire more (through a nested spin): kept apart */
  for (i = 0; i < n; ++i) {
    PyObject * route = Py_NewRef(PyList_GET_ITEM(fired, i));
    int failed = run_one(self, (RouteObject *)route, NULL) < 0;
    Py_DECREF(route);
    if (failed) {
      /* The rest goes back in front of whatever was fired meanwhile. */
      PyObject * et, * ev, * tb;
      PyErr_Fetch(&et, &ev, &tb);
      if (PyList_SetSlice(fired, 0, i + 1, NULL) < 0 ||
          PyList_SetSlice(self->fired, 0, 0, fired) < 0) {
        PyErr_Clear();
      }
      Py_DECREF(fired);
      PyErr_Restore(et, ev, tb);
      return NULL;
    }
  }
  Py_DECREF(fired);
  Py_RETURN_NONE;
}

static PyObject * Express_get_expressed(ExpressObject * self, void * Py_UNUSED(closure))
{
  return PyLong_FromUnsignedLongLong(self->expressed);
}

static PyMethodDef Express_methods[] = {
  {"drain", (PyCFunction)Express_drain, METH_O,
   "drain(deadline_ns) -> bool: take and run reported messages until none is, the deadline, or asyncio has work; False: take lock busy."},
  {"call_timers", (PyCFunction)(void (*)(void))Express_call_timers, METH_FASTCALL,
   "call_timers(routes, ready) -> list: call the ready timers that have routes (run by run_fired); the other addresses."},
  {"run_fired", (PyCFunction)Express_run_fired, METH_NOARGS,
   "run_fired() -> None: run the callbacks of the timers call_timers called."},
  {NULL, NULL, 0, NULL},
};

static PyGetSetDef Express_getset[] = {
  {"expressed", (getter)Express_get_expressed, NULL, "How many callbacks ran on this path.", NULL},
  {NULL, NULL, NULL, NULL, NULL},
};

PyTypeObject ExpressType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Express",
  .tp_doc = "The loop thread's chain of async subscription callbacks: take, admit, first step, release.",
  .tp_basicsize = sizeof(ExpressObject),
  .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Express_init,
  .tp_dealloc = (destructor)Express_dealloc,
  .tp_traverse = (traverseproc)Express_traverse,
  .tp_clear = (inquiry)Express_clear,
  .tp_methods = Express_methods,
  .tp_getset = Express_getset,
};

