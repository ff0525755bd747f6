/* Server and Caller: a service's requests and answers, and a client's
 * responses, taken and sent in C (see module.c). */
#include "fastpath.h"

typedef bool (*convert_from_py_t)(PyObject *, void *);

/* rmw's words when a client's response reader is not matched (yet). */
#define NOT_MATCHED "will not receive response"

/* The capsules of srv_type's ``part`` (Request or Response) that are asked for. */
static int message_functions(
  PyObject * srv_type, const char * part, PyObject ** type, create_message_t * create,
  destroy_message_t * destroy, convert_to_py_t * to_py, convert_from_py_t * from_py)
{
  PyObject * message_type = PyObject_GetAttrString(srv_type, part);
  int ok;
  if (message_type == NULL) {
    return -1;
  }
  ok = (create == NULL || (*create = (create_message_t)capsule_of(message_type, "_CREATE_ROS_MESSAGE")) != NULL)
    && (destroy == NULL || (*destroy = (destroy_message_t)capsule_of(message_type, "_DESTROY_ROS_MESSAGE")) != NULL)
    && (to_py == NULL || (*to_py = (convert_to_py_t)capsule_of(message_type, "_CONVERT_TO_PY")) != NULL)
    && (from_py == NULL || (*from_py = (convert_from_py_t)capsule_of(message_type, "_CONVERT_FROM_PY")) != NULL);
  if (ok && type != NULL) {
    *type = message_type;
    return 0;
  }
  Py_DECREF(message_type);
  return ok ? 0 : -1;
}

/* ------------------------------------------------------------------------ */
/* Server: one service's requests, taken into a kept C message, and its answers. */
typedef struct {
  PyObject_HEAD
  const rcl_service_t * service;
  void * request;
  destroy_message_t destroy_request;
  convert_to_py_t request_to_py;
  PyObject * response_type;
  create_message_t create_response;
  destroy_message_t destroy_response;
  convert_from_py_t response_from_py;
} ServerObject;

static int Server_init(ServerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"service", "srv_type", NULL};
  unsigned long long service;
  PyObject * srv_type;
  create_message_t create_request;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "$KO", keywords, &service, &srv_type)) {
    return -1;
  }
  if (service == 0 || self->request != NULL) {
    PyErr_SetString(PyExc_ValueError, "Server needs an rcl service's address, once");
    return -1;
  }
  if (message_functions(
        srv_type, "Request", NULL, &create_request, &self->destroy_request, &self->request_to_py, NULL) < 0 ||
      message_functions(
        srv_type, "Response", &self->response_type, &self->create_response, &self->destroy_response, NULL,
        &self->response_from_py) < 0)
  {
    return -1;
  }
  if ((self->request = create_request()) == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  self->service = (const rcl_service_t *)(uintptr_t)service;
  return 0;
}

static void Server_dealloc(ServerObject * self)
{
  if (self->request != NULL) {
    self->destroy_request(self->request);
  }
  Py_XDECREF(self->response_type);
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* take() -> (request, header) | None; the header is opaque (bytes), for send(). */
static PyObject * Server_take(ServerObject * self, PyObject * Py_UNUSED(ignored))
{
  rmw_service_info_t info;
  rcl_ret_t ret;
  PyObject * request, * header;
  if (self->request == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Server not initialised");
    return NULL;
  }
  ret = rcl_take_request_with_info(self->service, &info, self->request);
  if (ret == RCL_RET_SERVICE_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take_request_with_info");
  }
  if ((request = self->request_to_py(self->request)) == NULL) {
    return NULL;
  }
  header = PyBytes_FromStringAndSize((const char *)&info.request_id, sizeof(info.request_id));
  if (header == NULL) {
    Py_DECREF(request);
    return NULL;
  }
  return Py_BuildValue("(NN)", request, header);
}

/* send(response, header, let_go=False) -> bool: False when the client's
 * response reader is not matched (yet): rmw timed out waiting for it, up to
 * 100 ms. With let_go, the GIL is let go meanwhile (a thread that retries
 * such answers; the dispatching threads keep it, as rclpy does: a send that
 * lets go may wait for the GIL behind a busy thread). A response of another
 * type is a TypeError, as in rclpy. */
static PyObject * Server_send(ServerObject * self, PyObject * const * args, Py_ssize_t nargs)
{
  rmw_request_id_t header;
  char * bytes;
  Py_ssize_t size;
  void * message;
  rcl_ret_t ret;
  int is_response, let_go = 0;
  if (nargs < 2 || nargs > 3 || !PyBytes_Check(args[1])) {
    PyErr_SetString(PyExc_TypeError, "send(response, header, let_go=False), the header from take()");
    return NULL;
  }
  if (nargs == 3 && (let_go = PyObject_IsTrue(args[2])) < 0) {
    return NULL;
  }
  if (self->request == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Server not initialised");
    return NULL;
  }
  if (PyBytes_AsStringAndSize(args[1], &bytes, &size) < 0) {
    return NULL;
  }
  if (size != (Py_ssize_t)sizeof(header)) {
    PyErr_SetString(PyExc_ValueError, "not a header from take()");
    return NULL;
  }
  memcpy(&header, bytes, sizeof(header));
  if ((is_response = PyObject_IsInstance(args[0], self->response_type)) <= 0) {
    if (is_response == 0) {
      PyErr_Format(
        PyExc_TypeError, "a service callback returned %.200s, not %.200s", Py_TYPE(args[0])->tp_name,
        ((PyTypeObject *)self->response_type)->tp_name);
    }
    return NULL;
  }
  if ((message = self->create_response()) == NULL) {
    return PyErr_NoMemory();
  }
  if (!self->response_from_py(args[0], message)) {
    self->destroy_response(message);
    if (!PyErr_Occurred()) {
      PyErr_SetString(PyExc_ValueError, "the response could not be converted");
    }
    return NULL;
  }
  if (let_go) {
    Py_BEGIN_ALLOW_THREADS
    ret = rcl_send_response(self->service, &header, message);
    Py_END_ALLOW_THREADS
  } else {
    ret = rcl_send_response(self->service, &header, message);
  }
  self->destroy_response(message);
  if (ret == RCL_RET_OK) {
    Py_RETURN_TRUE;
  }
  /* Fast DDS's rmw waits 100 ms for the client's response reader, then
   * fails: a timeout (Jazzy), or an error saying so. */
  if (ret == RCL_RET_TIMEOUT || strstr(rcl_get_error_string().str, NOT_MATCHED) != NULL) {
    rcl_reset_error();
    Py_RETURN_FALSE;
  }
  return rcl_failed("rcl_send_response");
}

static PyMethodDef Server_methods[] = {
  {"take", (PyCFunction)Server_take, METH_NOARGS, "take() -> (request, header) | None"},
  {"send", (PyCFunction)(void (*)(void))Server_send, METH_FASTCALL,
   "send(response, header, let_go=False) -> bool: False while the client's response reader is not matched"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject ServerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Server",
  .tp_doc = "One rcl service's requests taken into a kept C message, and its answers sent.",
  .tp_basicsize = sizeof(ServerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Server_init,
  .tp_dealloc = (destructor)Server_dealloc,
  .tp_methods = Server_methods,
};

/* ------------------------------------------------------------------------ */
/* Caller: one client's responses, taken into a kept C message. */
typedef struct {
  PyObject_HEAD
  const rcl_client_t * client;
  void * response;
  destroy_message_t destroy;
  convert_to_py_t to_py;
} CallerObject;

static int Caller_init(CallerObject * self, PyObject * args, PyObject * kwargs)
{
  static char * keywords[] = {"client", "srv_type", NULL};
  unsigned long long client;
  PyObject * srv_type;
  create_message_t create;
  if (!PyArg_ParseTupleAndKeywords(args, kwargs, "$KO", keywords, &client, &srv_type)) {
    return -1;
  }
  if (client == 0 || self->response != NULL) {
    PyErr_SetString(PyExc_ValueError, "Caller needs an rcl client's address, once");
    return -1;
  }
  if (message_functions(srv_type, "Response", NULL, &create, &self->destroy, &self->to_py, NULL) < 0) {
    return -1;
  }
  if ((self->response = create()) == NULL) {
    PyErr_NoMemory();
    return -1;
  }
  self->client = (const rcl_client_t *)(uintptr_t)client;
  return 0;
}

static void Caller_dealloc(CallerObject * self)
{
  if (self->response != NULL) {
    self->destroy(self->response);
  }
  Py_TYPE(self)->tp_free((PyObject *)self);
}

/* take() -> (sequence_number, response) | None */
static PyObject * Caller_take(CallerObject * self, PyObject * Py_UNUSED(ignored))
{
  rmw_service_info_t info;
  rcl_ret_t ret;
  PyObject * response;
  if (self->response == NULL) {
    PyErr_SetString(PyExc_RuntimeError, "Caller not initialised");
    return NULL;
  }
  ret = rcl_take_response_with_info(self->client, &info, self->response);
  if (ret == RCL_RET_CLIENT_TAKE_FAILED) {
    Py_RETURN_NONE;
  }
  if (ret != RCL_RET_OK) {
    return rcl_failed("rcl_take_response_with_info");
  }
  if ((response = self->to_py(self->response)) == NULL) {
    return NULL;
  }
  return Py_BuildValue("(LN)", (long long)info.request_id.sequence_number, response);
}

static PyMethodDef Caller_methods[] = {
  {"take", (PyCFunction)Caller_take, METH_NOARGS, "take() -> (sequence_number, response) | None"},
  {NULL, NULL, 0, NULL},
};

PyTypeObject CallerType = {
  PyVarObject_HEAD_INIT(NULL, 0)
  .tp_name = "container.executor._fastpath.Caller",
  .tp_doc = "One rcl client's responses taken into a kept C message.",
  .tp_basicsize = sizeof(CallerObject),
  .tp_flags = Py_TPFLAGS_DEFAULT,
  .tp_new = PyType_GenericNew,
  .tp_init = (initproc)Caller_init,
  .tp_dealloc = (destructor)Caller_dealloc,
  .tp_methods = Caller_methods,
};
